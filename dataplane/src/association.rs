//! Geometric data association (paper Eq. 2-4) and the full score (Eq. 5-7), the
//! compiled twin of `swarmrec/core/association.py` (the reference).
//!
//! Every floating-point operation is the reference's, in the reference's order:
//! distances summed from 0.0 coordinate by coordinate (x, y, z), then `sqrt`;
//! surroundings distances summed over the common labels in label order; the
//! semantic score `common / (a + b - common)` and the score `sem * (matches /
//! common)`. Rust neither reorders nor fuses these (no fast-math, no FMA
//! contraction), so every score is the reference's bit for bit; the property
//! test `tests/integration/test_dataplane_verifier.py` checks it on random
//! frames.
//!
//! One difference in layout, none in value: the reference keeps a row of
//! `n_labels` nearest distances per object (inf for labels its frame lacks);
//! only the labels present in the frame are ever read (a common label is
//! present in both frames), so a [`Frame`] keeps those columns alone.

/// One constellation packed for association, computed once when it is stored.
#[derive(Clone, Debug)]
pub struct Frame {
    /// Label of each object, in detection order.
    pub labels: Vec<u32>,
    /// Object indices sorted by label, ties in detection order (a stable sort).
    pub order: Vec<u32>,
    /// Labels present in the frame, increasing, with their object counts.
    pub present: Vec<(u32, u32)>,
    /// `near[o * present.len() + k]`: distance from object o to the nearest object
    /// of label `present[k].0` in this frame (itself included: 0 for its own label).
    pub near: Vec<f64>,
}

impl Frame {
    /// Packs objects `labels[k]` at `positions[3k..3k+3]` (metres).
    pub fn new(labels: &[u32], positions: &[f64]) -> Frame {
        let n = labels.len();
        assert_eq!(positions.len(), 3 * n, "three coordinates per object");
        let mut order: Vec<u32> = (0..n as u32).collect();
        order.sort_by_key(|&o| labels[o as usize]); // stable: ties keep detection order
        let mut present: Vec<(u32, u32)> = Vec::new();
        for &o in &order {
            let l = labels[o as usize];
            match present.last_mut() {
                Some((last, count)) if *last == l => *count += 1,
                _ => present.push((l, 1)),
            }
        }
        let w = present.len();
        let mut near = vec![f64::INFINITY; n * w];
        for a in 0..n {
            for b in 0..n {
                let mut s = 0.0f64;
                for c in 0..3 {
                    let diff = positions[3 * a + c] - positions[3 * b + c];
                    s += diff * diff;
                }
                let dist = s.sqrt();
                let k = column(&present, labels[b]).expect("own label is present");
                if dist < near[a * w + k] {
                    near[a * w + k] = dist;
                }
            }
        }
        Frame {
            labels: labels.to_vec(),
            order,
            present,
            near,
        }
    }

    pub fn n_objects(&self) -> usize {
        self.labels.len()
    }

    /// Objects of `label` in the frame (its semantic descriptor's bin).
    pub fn count(&self, label: u32) -> u32 {
        column(&self.present, label).map_or(0, |k| self.present[k].1)
    }
}

fn column(present: &[(u32, u32)], label: u32) -> Option<usize> {
    present.binary_search_by_key(&label, |&(l, _)| l).ok()
}

/// Association knobs (a preset's `d`, `min_common`, `same_label_only`).
#[derive(Clone, Copy, Debug)]
pub struct Knobs {
    pub d: f64,
    pub min_common: u32,
    pub same_label_only: bool,
}

/// Frame `a` compared with frame `b`: the reference's `_pair` on two one-frame tables.
#[derive(Clone, Debug, PartialEq)]
pub struct PairScore {
    pub score: f64,
    pub semantic: f64,
    /// Matched (object of a, object of b), detection indices, in a's label order.
    pub matches: Vec<(u32, u32)>,
    /// Objects in common: the sum over labels of the smaller count.
    pub n_common: u32,
}

/// Eq. 2-7 for frame `a` against frame `b` (argument order matters for ties).
pub fn score_pair(a: &Frame, b: &Frame, knobs: Knobs) -> PairScore {
    // Common labels in label order, each with its column in a and in b.
    let mut common: Vec<(usize, usize)> = Vec::new();
    let mut sm: u64 = 0;
    let (mut i, mut j) = (0, 0);
    while i < a.present.len() && j < b.present.len() {
        let (la, ca) = a.present[i];
        let (lb, cb) = b.present[j];
        if la == lb {
            sm += u64::from(ca.min(cb));
            common.push((i, j));
            i += 1;
            j += 1;
        } else if la < lb {
            i += 1;
        } else {
            j += 1;
        }
    }
    let n_common = sm as u32;
    if sm == 0 {
        return PairScore {
            score: 0.0,
            semantic: 0.0,
            matches: Vec::new(),
            n_common,
        };
    }
    let (sa, sb) = (a.n_objects() as u64, b.n_objects() as u64);
    let sem = sm as f64 / (sa + sb - sm) as f64;
    if sm < u64::from(knobs.min_common) {
        return PairScore {
            score: 0.0,
            semantic: sem,
            matches: Vec::new(),
            n_common,
        };
    }
    let buf_a: Vec<u32> = a
        .order
        .iter()
        .copied()
        .filter(|&o| b.count(a.labels[o as usize]) > 0)
        .collect();
    let buf_b: Vec<u32> = b
        .order
        .iter()
        .copied()
        .filter(|&o| a.count(b.labels[o as usize]) > 0)
        .collect();
    let (ka, kb) = (buf_a.len(), buf_b.len());
    let (wa, wb) = (a.present.len(), b.present.len());
    let mut dist = vec![0.0f64; ka * kb];
    for x in 0..ka {
        let row_a = &a.near[buf_a[x] as usize * wa..][..wa];
        for y in 0..kb {
            let row_b = &b.near[buf_b[y] as usize * wb..][..wb];
            let mut s = 0.0f64;
            for &(ca, cb) in &common {
                let diff = row_a[ca] - row_b[cb];
                s += diff * diff;
            }
            dist[x * kb + y] = s.sqrt();
        }
    }
    let same = |x: usize, y: usize| a.labels[buf_a[x] as usize] == b.labels[buf_b[y] as usize];
    // Each object's nearest vector in the other frame; the first index wins a tie.
    let mut best_a = vec![usize::MAX; ka];
    for (x, best_x) in best_a.iter_mut().enumerate() {
        let mut best = usize::MAX;
        for y in 0..kb {
            if knobs.same_label_only && !same(x, y) {
                continue;
            }
            if best == usize::MAX || dist[x * kb + y] < dist[x * kb + best] {
                best = y;
            }
        }
        *best_x = best;
    }
    let mut best_b = vec![usize::MAX; kb];
    for (y, best_y) in best_b.iter_mut().enumerate() {
        let mut best = usize::MAX;
        for x in 0..ka {
            if knobs.same_label_only && !same(x, y) {
                continue;
            }
            if best == usize::MAX || dist[x * kb + y] < dist[best * kb + y] {
                best = x;
            }
        }
        *best_y = best;
    }
    let mut matches = Vec::new();
    for x in 0..ka {
        let y = best_a[x];
        if y != usize::MAX && best_b[y] == x && dist[x * kb + y] < knobs.d {
            matches.push((buf_a[x], buf_b[y]));
        }
    }
    let count = matches.len() as u64;
    let score = sem * (count as f64 / sm as f64);
    PairScore {
        score,
        semantic: sem,
        matches,
        n_common,
    }
}

/// A stored frame compared with a query, as `swarmrec.core.verification.FrameMatch`.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameMatch {
    pub frame: u32,
    pub score: f64,
    /// (object of the query, object of the stored frame).
    pub pairs: Vec<(u32, u32)>,
    pub n_common: u32,
    pub n_union: u32,
}

/// The reference's `verify_tables`: the query against each stored frame of `own_robot`,
/// each pair scored with the frame first in (robot, frame) order as first argument (the
/// offline evaluation's order); every result, best first, ties by frame index.
pub fn verify<'a>(
    query: &Frame,
    query_key: (u32, u32),
    own_robot: u32,
    frames: impl IntoIterator<Item = (u32, &'a Frame)>,
    knobs: Knobs,
) -> Vec<FrameMatch> {
    let mut out: Vec<FrameMatch> = frames
        .into_iter()
        .map(|(frame, stored)| {
            let first_is_query = query_key < (own_robot, frame);
            let s = if first_is_query {
                score_pair(query, stored, knobs)
            } else {
                score_pair(stored, query, knobs)
            };
            let pairs = if first_is_query {
                s.matches
            } else {
                s.matches.into_iter().map(|(p, q)| (q, p)).collect()
            };
            let n_union = (query.n_objects() + stored.n_objects()) as u32 - s.n_common;
            FrameMatch {
                frame,
                score: s.score,
                pairs,
                n_common: s.n_common,
                n_union,
            }
        })
        .collect();
    // Scores are finite (sums of finite positions' distances), so the order is total.
    out.sort_by(|x, y| {
        y.score
            .partial_cmp(&x.score)
            .expect("finite scores")
            .then(x.frame.cmp(&y.frame))
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const PAPER: Knobs = Knobs {
        d: 0.25,
        min_common: 3,
        same_label_only: false,
    };

    fn frame(objects: &[(u32, [f64; 3])]) -> Frame {
        let labels: Vec<u32> = objects.iter().map(|o| o.0).collect();
        let pos: Vec<f64> = objects.iter().flat_map(|o| o.1).collect();
        Frame::new(&labels, &pos)
    }

    #[test]
    fn a_frame_matches_itself_completely() {
        let f = frame(&[(0, [0.0, 0.0, 1.0]), (1, [1.0, 0.0, 2.0]), (2, [0.0, 1.0, 3.0])]);
        let s = score_pair(&f, &f, PAPER);
        assert_eq!(s.score, 1.0);
        assert_eq!(s.semantic, 1.0);
        assert_eq!(s.matches, vec![(0, 0), (1, 1), (2, 2)]);
    }

    #[test]
    fn too_few_common_objects_score_zero_but_keep_the_semantic_score() {
        let a = frame(&[(0, [0.0, 0.0, 1.0]), (1, [1.0, 0.0, 2.0]), (5, [0.0, 1.0, 3.0])]);
        let b = frame(&[(0, [0.0, 0.0, 1.0]), (1, [1.0, 0.0, 2.0]), (6, [0.0, 1.0, 3.0])]);
        let s = score_pair(&a, &b, PAPER);
        assert_eq!((s.score, s.n_common), (0.0, 2));
        assert_eq!(s.semantic, 2.0 / 4.0);
    }

    #[test]
    fn surroundings_vectors_match_under_a_rigid_motion_and_not_past_d() {
        // The same three objects moved 5 m: surroundings vectors are distances within a
        // frame, so they match; a fourth object 1 m off in one frame only breaks its own match.
        let a = frame(&[
            (0, [0.0, 0.0, 1.0]),
            (1, [1.0, 0.0, 2.0]),
            (2, [0.0, 1.0, 3.0]),
            (3, [2.0, 2.0, 2.0]),
        ]);
        let b = frame(&[
            (0, [5.0, 0.0, 1.0]),
            (1, [6.0, 0.0, 2.0]),
            (2, [5.0, 1.0, 3.0]),
            (3, [8.0, 2.0, 2.0]),
        ]);
        let s = score_pair(&a, &b, PAPER);
        assert_eq!(s.n_common, 4);
        assert!(s.matches.len() < 4, "the moved object must not match: {:?}", s.matches);
        assert_eq!(s.score, 1.0 * (s.matches.len() as f64 / 4.0));
    }

    #[test]
    fn verify_orders_best_first_then_by_frame_and_swaps_pairs_for_earlier_frames() {
        let q = frame(&[(0, [0.0, 0.0, 1.0]), (1, [1.0, 0.0, 2.0]), (2, [0.0, 1.0, 3.0])]);
        let other = frame(&[(0, [0.0, 0.0, 1.0]), (1, [1.0, 0.0, 2.0]), (4, [0.0, 1.0, 3.0])]);
        let stored = [(7u32, q.clone()), (3, q.clone()), (5, other)];
        let out = verify(&q, (1, 4), 1, stored.iter().map(|(f, fr)| (*f, fr)), PAPER);
        let order: Vec<u32> = out.iter().map(|m| m.frame).collect();
        assert_eq!(order, vec![3, 7, 5]);
        assert_eq!(out[0].pairs, vec![(0, 0), (1, 1), (2, 2)]);
        assert_eq!((out[2].n_common, out[2].n_union, out[2].score), (2, 4, 0.0));
    }
}
