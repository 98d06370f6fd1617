//! The index of one label range: the compiled twin of `swarmrec/core/index.py`
//! (`RangeIndex`, the reference), for the compiled index shard.
//!
//! Rows are stored compactly, one per stored (robot, frame), so memory and a query's
//! work follow what is stored, never the frame indices a request claims. A query scores
//! its slice against every stored row with the partial Jaccard index and keeps the
//! `n_ret` best scores > 0:
//!
//! * the score is the reference's operations in its order: `common` (the sum of the
//!   bin-wise minima; sums of small integers, exact in any order), `total = row sum +
//!   query sum - common`, `common / (total + 1e-12)`: the same doubles;
//! * in lock-step (`before = Some(t)`) the candidates are the published evaluation's:
//!   robot-major slots `robot * t + frame` over frames below `t`, and when equal scores
//!   straddle the cut, numpy's own argsort of the dense slot vector decides
//!   ([`crate::selection::select_candidates`]), exactly as the reference builds it;
//! * without a step, equal scores at the cut are kept in slot order;
//! * the answer is best first, equal scores in slot order.
//!
//! `tests/integration/test_dataplane_index.py` compares it with the reference on random
//! tie-heavy stores and queries.
use std::collections::HashMap;

use crate::selection::select_candidates;

/// The published scripts add this to every partial-score denominator; it changes the
/// order of equal fractions (2/4 ranks above 1/2), so it is kept.
pub const PARTIAL_EPSILON: f64 = 1e-12;

/// One kept candidate: a stored frame and its partial score.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    pub robot: u32,
    pub frame: u64,
    pub score: f64,
}

/// Partial descriptors of labels `[lo, hi)` from robots `0 .. n_robots`.
pub struct RangeIndex {
    pub lo: u32,
    pub hi: u32,
    pub n_robots: u32,
    /// Row-major counts, `width` a row, rows in arrival order.
    counts: Vec<f64>,
    sums: Vec<f64>,
    robot: Vec<u32>,
    frame: Vec<u64>,
    /// (robot, frame) -> row.
    rows: HashMap<(u32, u64), usize>,
    /// One past each robot's highest stored frame.
    frames: Vec<u64>,
}

impl RangeIndex {
    pub fn new(lo: u32, hi: u32, n_robots: u32) -> anyhow::Result<RangeIndex> {
        anyhow::ensure!(lo < hi, "empty label range [{lo}, {hi})");
        anyhow::ensure!(n_robots >= 1, "need at least one robot, got {n_robots}");
        Ok(RangeIndex {
            lo,
            hi,
            n_robots,
            counts: Vec::new(),
            sums: Vec::new(),
            robot: Vec::new(),
            frame: Vec::new(),
            rows: HashMap::new(),
            frames: vec![0; n_robots as usize],
        })
    }

    pub fn width(&self) -> usize {
        (self.hi - self.lo) as usize
    }

    /// Stored rows.
    pub fn size(&self) -> usize {
        self.robot.len()
    }

    /// One past the highest frame stored for `robot`.
    pub fn frames_of(&self, robot: u32) -> u64 {
        self.frames.get(robot as usize).copied().unwrap_or(0)
    }

    /// One past the highest frame stored for any robot.
    pub fn frames(&self) -> u64 {
        self.frames.iter().copied().max().unwrap_or(0)
    }

    /// The stored slice of `robot`'s frame `frame`.
    pub fn get(&self, robot: u32, frame: u64) -> Option<&[f64]> {
        let w = self.width();
        self.rows
            .get(&(robot, frame))
            .map(|&r| &self.counts[r * w..(r + 1) * w])
    }

    /// Stored rows `[start, stop)` in arrival order: (robot, frame, slice).
    pub fn rows(&self, start: usize, stop: usize) -> Vec<(u32, u64, &[f64])> {
        let w = self.width();
        (start..stop.min(self.size()))
            .map(|r| (self.robot[r], self.frame[r], &self.counts[r * w..(r + 1) * w]))
            .collect()
    }

    /// Stores (or replaces) a frame's slice; true when it was new.
    pub fn add(&mut self, robot: u32, frame: u64, counts: &[f64]) -> anyhow::Result<bool> {
        anyhow::ensure!(
            counts.len() == self.width(),
            "slice of {} bins for a range of {}",
            counts.len(),
            self.width()
        );
        anyhow::ensure!(
            robot < self.n_robots && frame < (1u64 << 32),
            "(robot {robot}, frame {frame}) is outside {} robots' frames",
            self.n_robots
        );
        let w = self.width();
        let (row, new) = match self.rows.get(&(robot, frame)) {
            Some(&r) => (r, false),
            None => {
                let r = self.size();
                self.rows.insert((robot, frame), r);
                self.robot.push(robot);
                self.frame.push(frame);
                self.counts.resize((r + 1) * w, 0.0);
                self.sums.push(0.0);
                (r, true)
            }
        };
        self.counts[row * w..(row + 1) * w].copy_from_slice(counts);
        // numpy sums a row of small integers: exact, so any order gives its double.
        self.sums[row] = counts.iter().sum();
        let f = &mut self.frames[robot as usize];
        *f = (*f).max(frame + 1);
        Ok(new)
    }

    /// The `n_ret` best stored frames for the query slice `query`, best first.
    pub fn candidates(&self, query: &[f64], n_ret: usize, before: Option<u64>) -> Vec<Candidate> {
        self.candidates_except(query, n_ret, before, None)
    }

    /// `candidates`, never naming the stored frame `except` (robot, frame): a frame is
    /// never its own candidate, even where its slice got here before its query did.
    pub fn candidates_except(
        &self,
        query: &[f64],
        n_ret: usize,
        before: Option<u64>,
        except: Option<(u32, u64)>,
    ) -> Vec<Candidate> {
        let t = before.unwrap_or_else(|| self.frames());
        if t == 0 {
            return Vec::new();
        }
        let w = self.width();
        let bins: Vec<usize> = (0..w.min(query.len())).filter(|&b| query[b] != 0.0).collect();
        let query_sum: f64 = query.iter().sum();
        let mut values: Vec<f64> = Vec::new();
        let mut slots: Vec<u64> = Vec::new();
        for r in 0..self.size() {
            if (before.is_some() && self.frame[r] >= t) || except == Some((self.robot[r], self.frame[r])) {
                continue;
            }
            let row = &self.counts[r * w..(r + 1) * w];
            let common: f64 = bins.iter().map(|&b| row[b].min(query[b])).sum();
            let total = self.sums[r] + query_sum - common;
            let value = common / (total + PARTIAL_EPSILON);
            if value > 0.0 {
                values.push(value);
                slots.push(u64::from(self.robot[r]) * t + self.frame[r]);
            }
        }
        let kept = self.select(&values, &slots, n_ret, before.map(|_| t));
        // Best first, equal scores in slot order.
        let mut chosen: Vec<(u64, f64)> = kept.into_iter().map(|i| (slots[i], values[i])).collect();
        chosen.sort_by(|a, b| b.1.total_cmp(&a.1).then(a.0.cmp(&b.0)));
        chosen
            .into_iter()
            .map(|(s, v)| Candidate {
                robot: (s / t) as u32,
                frame: s % t,
                score: v,
            })
            .collect()
    }

    /// Which of the positive `values` (at `slots`) are kept: with a step `t`, the published
    /// selection on the dense slot vector; without, equal scores at the cut in slot order.
    fn select(&self, values: &[f64], slots: &[u64], n_ret: usize, t: Option<u64>) -> Vec<usize> {
        let m = values.len();
        if m <= n_ret {
            return (0..m).collect();
        }
        let mut sorted = values.to_vec();
        let kth = *sorted.select_nth_unstable_by(m - n_ret, |a, b| a.total_cmp(b)).1;
        let keep: Vec<usize> = (0..m).filter(|&i| values[i] >= kth).collect();
        if keep.len() == n_ret {
            return keep;
        }
        match t {
            None => {
                let mut out: Vec<usize> = (0..m).filter(|&i| values[i] > kth).collect();
                let mut tied: Vec<usize> = (0..m).filter(|&i| values[i] == kth).collect();
                tied.sort_by_key(|&i| slots[i]);
                tied.truncate(n_ret - out.len());
                out.extend(tied);
                out
            }
            Some(t) => {
                // A tie straddles the cut: numpy's argsort of the dense vector (zeros
                // included) decides, so it is built, as the reference builds it.
                let mut dense = vec![0.0f64; self.n_robots as usize * t as usize];
                for (i, &s) in slots.iter().enumerate() {
                    dense[s as usize] = values[i];
                }
                let picked = select_candidates(&dense, n_ret);
                (0..m)
                    .filter(|&i| picked.binary_search(&(slots[i] as usize)).is_ok())
                    .collect()
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_best_scores_first() {
        let mut ix = RangeIndex::new(0, 3, 2).unwrap();
        ix.add(0, 0, &[1.0, 0.0, 0.0]).unwrap();
        ix.add(1, 0, &[1.0, 1.0, 0.0]).unwrap();
        ix.add(0, 1, &[0.0, 0.0, 2.0]).unwrap();
        let found = ix.candidates(&[1.0, 1.0, 0.0], 5, None);
        let order: Vec<(u32, u64)> = found.iter().map(|c| (c.robot, c.frame)).collect();
        assert_eq!(order, vec![(1, 0), (0, 0)]);
        assert!(found[0].score > found[1].score);
    }

    #[test]
    fn before_limits_every_robot_to_earlier_frames() {
        let mut ix = RangeIndex::new(0, 2, 2).unwrap();
        for f in 0..4 {
            ix.add(0, f, &[1.0, 0.0]).unwrap();
            ix.add(1, f, &[1.0, 1.0]).unwrap();
        }
        let found = ix.candidates(&[1.0, 0.0], 10, Some(2));
        assert_eq!(found.len(), 4);
        assert!(found.iter().all(|c| c.frame < 2));
    }

    #[test]
    fn the_excepted_frame_is_never_named_and_the_others_keep_their_order() {
        let mut ix = RangeIndex::new(0, 2, 2).unwrap();
        ix.add(0, 0, &[1.0, 0.0]).unwrap();
        ix.add(1, 0, &[1.0, 1.0]).unwrap();
        ix.add(1, 1, &[1.0, 1.0]).unwrap();
        let all: Vec<(u32, u64)> = ix
            .candidates(&[1.0, 1.0], 10, None)
            .iter()
            .map(|c| (c.robot, c.frame))
            .collect();
        assert_eq!(all, vec![(1, 0), (1, 1), (0, 0)]);
        let without: Vec<(u32, u64)> = ix
            .candidates_except(&[1.0, 1.0], 10, None, Some((1, 1)))
            .iter()
            .map(|c| (c.robot, c.frame))
            .collect();
        assert_eq!(without, vec![(1, 0), (0, 0)]);
    }

    #[test]
    fn a_stored_row_is_replaced_not_added() {
        let mut ix = RangeIndex::new(5, 7, 1).unwrap();
        assert!(ix.add(0, 3, &[1.0, 0.0]).unwrap());
        assert!(!ix.add(0, 3, &[0.0, 2.0]).unwrap());
        assert_eq!(ix.size(), 1);
        assert_eq!(ix.get(0, 3), Some(&[0.0, 2.0][..]));
        assert_eq!(ix.frames_of(0), 4);
    }

    #[test]
    fn bad_slices_and_ids_are_refused() {
        let mut ix = RangeIndex::new(0, 2, 2).unwrap();
        assert!(ix.add(0, 0, &[1.0]).is_err());
        assert!(ix.add(2, 0, &[1.0, 0.0]).is_err());
        assert!(ix.add(0, 1 << 32, &[1.0, 0.0]).is_err());
        assert!(RangeIndex::new(3, 3, 1).is_err());
    }
}
