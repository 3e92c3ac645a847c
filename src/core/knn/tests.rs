use super::*;

/// The definition, literally: order every entry, take the first k, sum in pool order.
fn knn_f_by_sort(dis: &[f64], xs: &[f64], seqs: &[u64], k: usize) -> f64 {
    let n = dis.len();
    let exact = dis.iter().filter(|&&d| d == 0.0).count();
    let p: Vec<f64> = if exact > 0 {
        let share = 1.0 / exact as f64;
        dis.iter()
            .map(|&d| if d == 0.0 { share } else { 0.0 })
            .collect()
    } else {
        let total: f64 = dis.iter().map(|&d| 1.0 / d).sum();
        dis.iter().map(|&d| (1.0 / d) / total).collect()
    };
    let mut idx: Vec<usize> = (0..n).collect();
    idx.sort_by(|&a, &b| {
        p[b].total_cmp(&p[a])
            .then_with(|| xs[b].total_cmp(&xs[a]))
            .then_with(|| seqs[a].cmp(&seqs[b]))
    });
    let mut top = idx[..k.min(n)].to_vec();
    top.sort_unstable();
    top.iter().map(|&i| xs[i] * p[i]).sum()
}

/// A tiny deterministic PRNG: `next(m)` is below m.
fn xorshift(mut state: u64) -> impl FnMut(u64) -> u64 {
    move |m| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state % m
    }
}

#[test]
fn selection_matches_the_definition_bit_for_bit() {
    // Small integer distances and few distinct scores: many ties in P and in x, and
    // one scratch across pools of different sizes and contents.
    let mut next = xorshift(0x2545_f491_4f6c_dd1d);
    let mut scratch = KnnScratch::default();
    for round in 0..3000 {
        let n = 1 + next(40) as usize;
        let dis: Vec<f64> = (0..n)
            .map(|_| match round % 3 {
                0 => 2.0 * next(4) as f64,
                1 => 2.0 * next(50) as f64,
                _ => next(1000) as f64 / 7.0,
            })
            .collect();
        let xs: Vec<f64> = (0..n).map(|_| next(4) as f64 / 3.0).collect();
        let mut seqs: Vec<u64> = (0..n).map(|_| next(1000)).collect();
        seqs.sort_unstable();
        seqs.dedup();
        let n = seqs.len();
        for k in [1, n / 2 + 1, n.saturating_sub(1).max(1), n] {
            let got = knn_f(&dis[..n], &xs[..n], &seqs, k, &mut scratch);
            let want = knn_f_by_sort(&dis[..n], &xs[..n], &seqs, k);
            assert_eq!(
                got.to_bits(),
                want.to_bits(),
                "n {n} k {k} dis {dis:?} xs {xs:?}"
            );
        }
    }
}

#[test]
fn discrete_selection_matches_the_definition_bit_for_bit() {
    let mut next = xorshift(0x9e37_79b9_7f4a_7c15);
    let mut scratch = KnnScratch::default();
    for round in 0..3000 {
        // Pools of up to 64 entries (K as a bit set) and larger ones.
        let n = 1 + next(if round % 5 == 4 { 150 } else { 64 }) as usize;
        let spread = [3, 50, 200, 3000][round % 4];
        let mut ms: Vec<u32> = (0..n).map(|_| next(spread) as u32).collect();
        let xs: Vec<f64> = (0..n).map(|_| next(4) as f64 / 3.0).collect();
        let mut seqs: Vec<u64> = (0..n).map(|_| next(1000)).collect();
        seqs.sort_unstable();
        seqs.dedup();
        let n = seqs.len();
        let mut idx: Vec<usize> = (0..n).collect();
        idx.sort_by(|&a, &b| xs[b].total_cmp(&xs[a]).then(seqs[a].cmp(&seqs[b])));
        let by_place: Vec<u32> = idx.iter().map(|&i| i as u32).collect();
        let mut place_of = vec![0u32; n];
        for (p, &i) in by_place.iter().enumerate() {
            place_of[i as usize] = p as u32;
        }
        let ks = [1, n / 2 + 1, n.saturating_sub(1).max(1), n];
        // One remembered k-th count per k, as an episode keeps it.
        let mut kths = [None; 4];
        // Several steps of one episode: counts grow by 0 or 1 (now and then by more,
        // as after steps without the kNN term), the order is kept.
        for step in 0..8 {
            for (&k, kth) in ks.iter().zip(&mut kths) {
                // Now and then a stale or wrong remembered count: it must not matter.
                if next(7) == 0 {
                    *kth = Some(next(spread + 2) as u32);
                }
                let got = knn_f_discrete(
                    &ms[..n],
                    &xs[..n],
                    &by_place,
                    &place_of,
                    k,
                    &mut scratch,
                    kth,
                );
                let dis: Vec<f64> = ms[..n].iter().map(|&m| 2.0 * f64::from(m)).collect();
                let want = knn_f_by_sort(&dis, &xs[..n], &seqs, k);
                assert_eq!(got.to_bits(), want.to_bits(), "n {n} k {k}");
            }
            let jump = if step % 4 == 3 { 4 } else { 2 };
            ms.iter_mut().for_each(|m| *m += next(jump) as u32);
        }
    }
}

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
