//! numpy's default `argsort`, tie for tie.
//!
//! The published scripts keep the first `n_ret` candidates (and `n_fq` robots) of a
//! descending `numpy.argsort`, and numpy's default sort is not stable: among equal
//! scores, which are kept is whatever the sort numpy runs leaves first. To keep the
//! offline evaluation's candidates a compiled service must run that same sort
//! (`bench/tie_rule.py` measured that no stated rule does: ties straddle most cuts).
//!
//! numpy 2.4.6 sorts 64-bit keys with one of three programs, picked per process
//! from the CPU and the `NPY_DISABLE_CPU_FEATURES` / `NPY_ENABLE_CPU_FEATURES`
//! variables: Intel's x86-simd-sort compiled for X86_V4 (AVX-512) or for X86_V3
//! (AVX2), or its own introsort. The first two are the vendored library itself
//! (`dataplane/vendor`, compiled by build.rs with numpy's flags); the third is
//! written out below from numpy's `aquicksort_` (median of three, insertion sort
//! under 16 elements, heapsort past twice the depth of a balanced tree).
//! `tests/integration/test_argsort.py` compares all three with numpy, on random
//! tied arrays, under each choice of those variables.
use std::sync::OnceLock;

/// The program numpy sorts 64-bit keys with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Level {
    /// x86-simd-sort's AVX-512 code (numpy's X86_V4 dispatch target).
    X86V4,
    /// x86-simd-sort's AVX2 code (numpy's X86_V3 dispatch target).
    X86V3,
    /// numpy's own introsort (no dispatch target available).
    Baseline,
}

impl Level {
    pub fn name(self) -> &'static str {
        match self {
            Level::X86V4 => "X86_V4",
            Level::X86V3 => "X86_V3",
            Level::Baseline => "baseline",
        }
    }

    pub fn parse(name: &str) -> Option<Level> {
        match name {
            "X86_V4" => Some(Level::X86V4),
            "X86_V3" => Some(Level::X86V3),
            "baseline" => Some(Level::Baseline),
            _ => None,
        }
    }

    /// The level numpy would sort with in this process (decided once).
    pub fn numpy() -> Level {
        static LEVEL: OnceLock<Level> = OnceLock::new();
        *LEVEL.get_or_init(|| {
            let enable = std::env::var("NPY_ENABLE_CPU_FEATURES").unwrap_or_default();
            let disable = std::env::var("NPY_DISABLE_CPU_FEATURES").unwrap_or_default();
            let (v3, v4) = cpu_levels();
            choose(v3, v4, &enable, &disable)
        })
    }
}

/// numpy's choice from what the CPU has and the two variables: a level is used when
/// the CPU has it and the variables leave it on, and X86_V4 only above X86_V3 (numpy
/// drops to its introsort when X86_V3 alone is disabled). Names other than the two
/// levels (numpy's older AVX2, AVX512_SKX, ...) do not change numpy 2.4's dispatch.
fn choose(cpu_v3: bool, cpu_v4: bool, enable: &str, disable: &str) -> Level {
    let listed = |list: &str, name: &str| list.split([' ', ',', '\t', '\n']).any(|t| t == name);
    let on = |name: &str| {
        let enabled = enable.trim().is_empty() || listed(enable, name);
        enabled && !listed(disable, name)
    };
    let v3 = cpu_v3 && on("X86_V3");
    let v4 = v3 && cpu_v4 && on("X86_V4");
    if v4 && cfg!(target_arch = "x86_64") {
        Level::X86V4
    } else if v3 && cfg!(target_arch = "x86_64") {
        Level::X86V3
    } else {
        Level::Baseline
    }
}

#[cfg(target_arch = "x86_64")]
fn cpu_levels() -> (bool, bool) {
    let v3 = is_x86_feature_detected!("avx")
        && is_x86_feature_detected!("avx2")
        && is_x86_feature_detected!("fma")
        && is_x86_feature_detected!("bmi1")
        && is_x86_feature_detected!("bmi2")
        && is_x86_feature_detected!("lzcnt")
        && is_x86_feature_detected!("f16c")
        && is_x86_feature_detected!("movbe");
    let v4 = is_x86_feature_detected!("avx512f")
        && is_x86_feature_detected!("avx512cd")
        && is_x86_feature_detected!("avx512vl")
        && is_x86_feature_detected!("avx512bw")
        && is_x86_feature_detected!("avx512dq");
    (v3, v4)
}

#[cfg(not(target_arch = "x86_64"))]
fn cpu_levels() -> (bool, bool) {
    (false, false)
}

#[cfg(target_arch = "x86_64")]
extern "C" {
    fn swarmrec_argsort_f64_x86_v4(arr: *mut f64, arg: *mut usize, n: usize);
    fn swarmrec_argsort_i64_x86_v4(arr: *mut i64, arg: *mut usize, n: usize);
    fn swarmrec_argsort_f64_x86_v3(arr: *mut f64, arg: *mut usize, n: usize);
    fn swarmrec_argsort_i64_x86_v3(arr: *mut i64, arg: *mut usize, n: usize);
}

/// A key type numpy sorts with x86-simd-sort: its two compiled programs and numpy's order.
pub trait Key: Copy {
    /// The vendored library's argsort of `n` keys at `arr` into `arg` at `level` (X86_V4 or
    /// X86_V3), which the CPU must have.
    ///
    /// # Safety
    /// `arr` and `arg` point to `n` elements each; the CPU has `level`.
    #[cfg(target_arch = "x86_64")]
    unsafe fn simd_argsort(level: Level, arr: *mut Self, arg: *mut usize, n: usize);
    /// numpy's `Tag::less` for the type.
    fn less(a: &Self, b: &Self) -> bool;
}

impl Key for f64 {
    #[cfg(target_arch = "x86_64")]
    unsafe fn simd_argsort(level: Level, arr: *mut f64, arg: *mut usize, n: usize) {
        if level == Level::X86V4 {
            swarmrec_argsort_f64_x86_v4(arr, arg, n)
        } else {
            swarmrec_argsort_f64_x86_v3(arr, arg, n)
        }
    }
    fn less(a: &f64, b: &f64) -> bool {
        double_less(a, b)
    }
}

impl Key for i64 {
    #[cfg(target_arch = "x86_64")]
    unsafe fn simd_argsort(level: Level, arr: *mut i64, arg: *mut usize, n: usize) {
        if level == Level::X86V4 {
            swarmrec_argsort_i64_x86_v4(arr, arg, n)
        } else {
            swarmrec_argsort_i64_x86_v3(arr, arg, n)
        }
    }
    fn less(a: &i64, b: &i64) -> bool {
        a < b
    }
}

/// `numpy.argsort(values)` (the default kind) as numpy sorts in this process.
pub fn argsort<T: Key>(values: &[T]) -> Vec<usize> {
    argsort_at(values, Level::numpy())
}

/// `numpy.argsort(values)` with the program of `level` (a level the CPU lacks runs
/// numpy's introsort instead of faulting).
pub fn argsort_at<T: Key>(values: &[T], level: Level) -> Vec<usize> {
    let mut arg: Vec<usize> = (0..values.len()).collect();
    if values.len() < 2 {
        return arg;
    }
    match available(level) {
        #[cfg(target_arch = "x86_64")]
        simd @ (Level::X86V4 | Level::X86V3) => {
            let mut copy = values.to_vec();
            // SAFETY: both buffers hold values.len() elements and outlive the call, the CPU
            // has `simd` (available); the library reads `copy` and permutes `arg`, nothing else.
            unsafe { T::simd_argsort(simd, copy.as_mut_ptr(), arg.as_mut_ptr(), copy.len()) }
        }
        _ => introsort(values, &mut arg, T::less),
    }
    arg
}

/// `level` if this CPU can run it, else the baseline (never an illegal instruction).
fn available(level: Level) -> Level {
    let (v3, v4) = cpu_levels();
    match level {
        Level::X86V4 if v3 && v4 => Level::X86V4,
        Level::X86V3 if v3 => Level::X86V3,
        _ => Level::Baseline,
    }
}

/// numpy's order for doubles: NaN after every number.
fn double_less(a: &f64, b: &f64) -> bool {
    #[allow(clippy::eq_op)]
    let b_nan_a_not = b.is_nan() && !a.is_nan();
    *a < *b || b_nan_a_not
}

/// Below this many elements minus one a partition is finished by insertion sort.
const SMALL_QUICKSORT: usize = 15;

/// numpy's `aquicksort_`: an introsort of the index array `arg` by `v[arg[i]]`.
/// Indices into `arg` stand for numpy's pointers; the explicit stack and the order
/// of every comparison and swap are numpy's, since they decide where ties land.
fn introsort<T: Copy>(v: &[T], arg: &mut [usize], less: impl Fn(&T, &T) -> bool) {
    let num = arg.len();
    let mut stack: Vec<(usize, usize, i32)> = Vec::new();
    let mut pl = 0usize;
    let mut pr = num - 1;
    let mut cdepth = 2 * msb(num);
    loop {
        if cdepth < 0 {
            heapsort(v, &mut arg[pl..=pr], &less);
        } else {
            while pr - pl > SMALL_QUICKSORT {
                let pm = pl + ((pr - pl) >> 1);
                if less(&v[arg[pm]], &v[arg[pl]]) {
                    arg.swap(pm, pl);
                }
                if less(&v[arg[pr]], &v[arg[pm]]) {
                    arg.swap(pr, pm);
                }
                if less(&v[arg[pm]], &v[arg[pl]]) {
                    arg.swap(pm, pl);
                }
                let vp = v[arg[pm]];
                let mut pi = pl;
                let mut pj = pr - 1;
                arg.swap(pm, pj);
                loop {
                    // Sentinels: v[arg[pr]] >= vp stops pi, v[arg[pl]] <= vp stops pj.
                    pi += 1;
                    while less(&v[arg[pi]], &vp) {
                        pi += 1;
                    }
                    pj -= 1;
                    while less(&vp, &v[arg[pj]]) {
                        pj -= 1;
                    }
                    if pi >= pj {
                        break;
                    }
                    arg.swap(pi, pj);
                }
                let pk = pr - 1;
                arg.swap(pi, pk);
                cdepth -= 1;
                // The larger side waits on the stack, the smaller is sorted next.
                if pi - pl < pr - pi {
                    stack.push((pi + 1, pr, cdepth));
                    pr = pi - 1;
                } else {
                    stack.push((pl, pi - 1, cdepth));
                    pl = pi + 1;
                }
            }
            for pi in pl + 1..=pr {
                let vi = arg[pi];
                let vp = v[vi];
                let mut pj = pi;
                while pj > pl && less(&vp, &v[arg[pj - 1]]) {
                    arg[pj] = arg[pj - 1];
                    pj -= 1;
                }
                arg[pj] = vi;
            }
        }
        match stack.pop() {
            None => break,
            Some((l, r, d)) => {
                pl = l;
                pr = r;
                cdepth = d;
            }
        }
    }
}

/// numpy's `aheapsort_` on one partition. Only an introsort partition that recursed past
/// twice the depth of a balanced tree gets here, which random arrays never do, and numpy
/// 2.4 no longer runs its heapsort on its own (`kind="heapsort"` runs the default sort),
/// so unlike the rest this is checked to sort, not against numpy's own picks. (1-based heap over `arg`).
fn heapsort<T: Copy>(v: &[T], arg: &mut [usize], less: &impl Fn(&T, &T) -> bool) {
    let mut n = arg.len();
    let mut l = n >> 1;
    while l > 0 {
        let tmp = arg[l - 1];
        sift_down(v, arg, l, n, tmp, less);
        l -= 1;
    }
    while n > 1 {
        let tmp = arg[n - 1];
        arg[n - 1] = arg[0];
        n -= 1;
        sift_down(v, arg, 1, n, tmp, less);
    }
}

/// One of numpy's sift-downs: `tmp` sinks from heap slot `i` of a heap of `n` (slots are
/// 1-based, as numpy offsets the array by one: slot k is `arg[k - 1]`), the larger child
/// rising, ties keeping the left one.
fn sift_down<T: Copy>(v: &[T], arg: &mut [usize], mut i: usize, n: usize, tmp: usize, less: &impl Fn(&T, &T) -> bool) {
    let mut j = i << 1;
    while j <= n {
        if j < n && less(&v[arg[j - 1]], &v[arg[j]]) {
            j += 1;
        }
        if less(&v[tmp], &v[arg[j - 1]]) {
            arg[i - 1] = arg[j - 1];
            i = j;
            j += j;
        } else {
            break;
        }
    }
    arg[i - 1] = tmp;
}

/// numpy's `npy_get_msb`: the index of the highest set bit (0 for 0 and 1).
fn msb(mut n: usize) -> i32 {
    let mut depth = 0;
    while n > 1 {
        n >>= 1;
        depth += 1;
    }
    depth
}

#[cfg(test)]
mod tests {
    use super::*;

    fn is_sorted_by(values: &[f64], arg: &[usize]) -> bool {
        let mut seen = vec![false; values.len()];
        for &i in arg {
            if seen[i] {
                return false;
            }
            seen[i] = true;
        }
        arg.windows(2).all(|w| !double_less(&values[w[1]], &values[w[0]]))
    }

    #[test]
    fn every_level_sorts() {
        // A permutation that orders the values, at every level and size, ties included.
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        for n in [0usize, 1, 2, 3, 15, 16, 17, 40, 255, 256, 257, 1000, 5000] {
            let values: Vec<f64> = (0..n)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    -((x % 5) as f64) / 4.0
                })
                .collect();
            for level in [Level::X86V4, Level::X86V3, Level::Baseline] {
                assert!(is_sorted_by(&values, &argsort_at(&values, level)), "{n} {level:?}");
                let ints: Vec<i64> = values.iter().map(|v| (*v * 4.0) as i64).collect();
                let arg = argsort_at(&ints, level);
                assert!(arg.windows(2).all(|w| ints[w[0]] <= ints[w[1]]), "{n} {level:?} int");
            }
        }
    }

    #[test]
    fn the_baseline_is_numpys_introsort_on_a_known_case() {
        // numpy 2.4.6 with NPY_DISABLE_CPU_FEATURES="X86_V4 X86_V3":
        // np.argsort(np.array([1., 0.] * 9)).tolist()
        let values: Vec<f64> = (0..18).map(|i| if i % 2 == 0 { 1.0 } else { 0.0 }).collect();
        let expected = [17, 1, 15, 3, 5, 13, 7, 9, 11, 14, 12, 0, 16, 6, 4, 2, 10, 8];
        assert_eq!(argsort_at(&values, Level::Baseline), expected);
    }

    #[test]
    fn numpys_dispatch_choice() {
        assert_eq!(choose(true, true, "", ""), Level::X86V4);
        assert_eq!(choose(true, true, "", "X86_V4"), Level::X86V3);
        assert_eq!(choose(true, true, "", "X86_V3"), Level::Baseline);
        assert_eq!(choose(true, true, "", "X86_V4,X86_V3"), Level::Baseline);
        assert_eq!(choose(true, true, "X86_V3", ""), Level::X86V3);
        assert_eq!(choose(true, true, "", "AVX2 AVX512_SKX"), Level::X86V4);
        assert_eq!(choose(true, false, "", ""), Level::X86V3);
        assert_eq!(choose(false, false, "", ""), Level::Baseline);
    }

    #[test]
    fn the_heapsort_fallback_sorts_tied_keys() {
        let mut x: u64 = 0x2545_F491_4F6C_DD1D;
        for n in [1usize, 2, 3, 7, 16, 100, 1000] {
            let values: Vec<f64> = (0..n)
                .map(|_| {
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    (x % 4) as f64
                })
                .collect();
            let mut arg: Vec<usize> = (0..n).collect();
            heapsort(&values, &mut arg, &double_less);
            assert!(is_sorted_by(&values, &arg), "{n}");
        }
    }

    #[test]
    fn nan_sorts_last_at_the_baseline() {
        let values = [f64::NAN, 1.0, -1.0, f64::NAN, 0.0];
        let arg = argsort_at(&values, Level::Baseline);
        assert_eq!(&arg[..3], &[2, 4, 1]);
    }
}
