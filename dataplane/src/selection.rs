//! Candidate selection by a range holder (`n_ret`) and robot selection by the
//! querying robot (`n_fq`): the compiled twin of `swarmrec/core/selection.py`.
//!
//! Both keep the first entries of a descending numpy argsort, so equal scores at the
//! cut are decided by numpy's own sort ([`crate::argsort`]); when no tie straddles
//! the cut the kept set does not depend on the sort, and it is skipped, as in the
//! reference.

use crate::argsort::argsort;

/// Indices of the (at most) `n_ret` best scores > 0, increasing, as the paper picks them:
/// `sorted(numpy.argsort(-scores)[:n_ret])` restricted to positive scores.
pub fn select_candidates(scores: &[f64], n_ret: usize) -> Vec<usize> {
    let positive: Vec<usize> = (0..scores.len()).filter(|&i| scores[i] > 0.0).collect();
    if positive.len() <= n_ret {
        return positive;
    }
    let kth = kth_smallest(positive.iter().map(|&i| scores[i]).collect(), positive.len() - n_ret);
    let kept: Vec<usize> = positive.iter().copied().filter(|&i| scores[i] >= kth).collect();
    if kept.len() == n_ret {
        return kept;
    }
    // A tie straddles the cut: numpy's sort of the whole negated vector decides.
    let negated: Vec<f64> = scores.iter().map(|s| -s).collect();
    let mut chosen = argsort(&negated);
    chosen.truncate(n_ret);
    chosen.sort_unstable();
    chosen
}

/// Robots to send the full constellation to: the `n_fq` robots with the most
/// candidates (ties as numpy's argsort of the negated counts orders them), plus the
/// querying robot (None: the query comes from outside the swarm); increasing, unique.
/// Robots with no candidate may fill the list, as in the published scripts.
pub fn select_robots(candidate_robots: &[usize], n_fq: usize, self_robot: Option<usize>) -> Vec<usize> {
    let mut chosen: Vec<usize> = Vec::new();
    if let Some(&max) = candidate_robots.iter().max() {
        let mut counts = vec![0i64; max + 1];
        for &r in candidate_robots {
            counts[r] += 1;
        }
        let negated: Vec<i64> = counts.iter().map(|c| -c).collect();
        chosen.extend(argsort(&negated).into_iter().take(n_fq));
    }
    chosen.extend(self_robot);
    chosen.sort_unstable();
    chosen.dedup();
    chosen
}

/// The value at position `k` of `values` sorted increasingly (`numpy.partition`'s kth).
fn kth_smallest(mut values: Vec<f64>, k: usize) -> f64 {
    *values.select_nth_unstable_by(k, |a, b| a.total_cmp(b)).1
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn few_positive_scores_are_all_kept() {
        assert_eq!(select_candidates(&[0.0, 0.5, 0.0, 0.2], 3), vec![1, 3]);
    }

    #[test]
    fn no_tie_at_the_cut_keeps_the_best() {
        assert_eq!(select_candidates(&[0.1, 0.5, 0.3, 0.2, 0.0], 2), vec![1, 2]);
    }

    #[test]
    fn a_tie_at_the_cut_keeps_n_ret() {
        let kept = select_candidates(&[0.5, 0.2, 0.2, 0.2, 0.0], 2);
        assert_eq!(kept.len(), 2);
        assert!(kept.contains(&0));
    }

    #[test]
    fn robots_with_most_candidates_and_self() {
        assert_eq!(select_robots(&[3, 3, 1, 3, 1, 0], 2, Some(5)), vec![1, 3, 5]);
        assert_eq!(select_robots(&[], 2, Some(4)), vec![4]);
        assert_eq!(select_robots(&[2], 3, None).len(), 3);
    }
}
