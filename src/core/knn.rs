//! The kNN reward r(t) of SPEC §3, given the distances of the current prefix to every
//! stored trajectory.

use std::cmp::Ordering;

/// r(t) = exp(f(t)) − exp(0.5).
pub fn reward_from_f(f: f64) -> f64 {
    f.exp() - 0.5f64.exp()
}

/// Reusable buffers for [`knn_f`], so a step allocates nothing.
#[derive(Debug, Default, Clone)]
pub struct KnnScratch {
    p: Vec<f64>,
    idx: Vec<usize>,
}

/// f(t) = Σ_{i∈K} x_i·P_i for distances `dis`, normalised scores `xs` and seqs `seqs`
/// (all aligned, non-empty), with K the first `k` entries ordered by P descending, then x
/// descending, then seq ascending. P is not renormalised over K.
///
/// The sum runs over K in ascending seq (= pool) order, so the result is reproducible bit
/// for bit. Cost: O(|D|) plus selecting the top k and sorting them (O(k log k)).
pub fn knn_f(dis: &[f64], xs: &[f64], seqs: &[u64], k: usize, scratch: &mut KnnScratch) -> f64 {
    let n = dis.len();
    debug_assert!(n > 0 && xs.len() == n && seqs.len() == n);
    let p = &mut scratch.p;
    p.clear();
    let exact = dis.iter().filter(|&&d| d == 0.0).count();
    if exact > 0 {
        // Exact prefix matches share the probability mass (the limit dis → 0).
        let share = 1.0 / exact as f64;
        p.extend(dis.iter().map(|&d| if d == 0.0 { share } else { 0.0 }));
    } else {
        let total: f64 = dis.iter().map(|&d| 1.0 / d).sum();
        p.extend(dis.iter().map(|&d| (1.0 / d) / total));
    }
    if k >= n {
        return p.iter().zip(xs).map(|(&pi, &xi)| xi * pi).sum();
    }
    let idx = &mut scratch.idx;
    idx.clear();
    idx.extend(0..n);
    let order = |&a: &usize, &b: &usize| -> Ordering {
        p[b].total_cmp(&p[a])
            .then_with(|| xs[b].total_cmp(&xs[a]))
            .then_with(|| seqs[a].cmp(&seqs[b]))
    };
    idx.select_nth_unstable_by(k - 1, order);
    let top = &mut idx[..k];
    top.sort_unstable();
    top.iter().map(|&i| xs[i] * p[i]).sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equidistant_from_best_and_worst_gives_zero() {
        // Two trajectories, x = 1 and x = 0, at equal distance: P = 1/2 each,
        // f = 0.5, r = e^0.5 − e^0.5 = 0.
        let f = knn_f(
            &[4.0, 4.0],
            &[1.0, 0.0],
            &[1, 2],
            2,
            &mut KnnScratch::default(),
        );
        assert_eq!(f, 0.5);
        assert_eq!(reward_from_f(f), 0.0);
    }

    #[test]
    fn exact_match_with_the_best_gives_e_minus_sqrt_e() {
        let f = knn_f(
            &[0.0, 2.0, 6.0],
            &[1.0, 0.0, 0.5],
            &[1, 2, 3],
            3,
            &mut KnnScratch::default(),
        );
        assert_eq!(f, 1.0);
        assert_eq!(reward_from_f(f), 1f64.exp() - 0.5f64.exp());
    }

    #[test]
    fn probabilities_are_not_renormalised_over_k() {
        // dis 1, 2, 4 -> inv 1, .5, .25 (sum 1.75); k = 1 keeps only the nearest.
        let f = knn_f(
            &[1.0, 2.0, 4.0],
            &[1.0, 1.0, 1.0],
            &[1, 2, 3],
            1,
            &mut KnnScratch::default(),
        );
        assert_eq!(f, 1.0 / 1.75);
    }

    #[test]
    fn ties_in_p_prefer_higher_score_then_lower_seq() {
        let mut s = KnnScratch::default();
        // Equal P; k = 1 takes the higher x.
        let f = knn_f(&[2.0, 2.0], &[0.25, 0.75], &[1, 2], 1, &mut s);
        assert_eq!(f, 0.75 * 0.5);
        // Two exact matches among three with k = 1: the one with the larger x wins.
        let f = knn_f(&[0.0, 0.0, 2.0], &[0.0, 0.5, 1.0], &[1, 2, 3], 1, &mut s);
        assert_eq!(f, 0.5 * 0.5);
    }
}
