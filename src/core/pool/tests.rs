use super::*;

fn acts(v: &[u32]) -> ActionSeq {
    ActionSeq::Discrete(v.to_vec())
}

/// A seeded xorshift: `next(m)` is a pseudo-random number below `m`.
fn xorshift(mut state: u64) -> impl FnMut(u64) -> u64 {
    move |m| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state % m
    }
}

fn offer(pool: &mut Pool, len: usize, score: f64) -> Option<PoolChange> {
    let change = pool.plan_offer(acts(&vec![0; len]), score);
    if let Some(c) = &change {
        pool.apply(c);
    }
    change
}

#[test]
fn inserts_until_full_then_replaces_strictly_better() {
    let mut p = Pool::new(2);
    assert!(offer(&mut p, 3, 1.0).is_some());
    assert!(offer(&mut p, 4, 1.0).is_some());
    assert_eq!(p.version(), 2);
    // Equal to the minimum: discarded, version unchanged.
    assert!(offer(&mut p, 5, 1.0).is_none());
    assert_eq!(p.version(), 2);
    // Better: replaces the lowest seq among the equal minima (seq 1).
    let c = offer(&mut p, 5, 2.0).unwrap();
    assert!(matches!(
        c,
        PoolChange::Insert {
            replaces: Some(1),
            ..
        }
    ));
    assert_eq!(p.seqs(), &[2, 3]);
    assert_eq!(p.l_min(), 4);
    assert_eq!(p.version(), 3);
}

#[test]
fn normalised_scores_and_equal_scores() {
    let mut p = Pool::new(3);
    offer(&mut p, 1, 5.0);
    assert_eq!(p.xs(), &[1.0]);
    offer(&mut p, 1, 1.0);
    offer(&mut p, 1, 2.0);
    assert_eq!(p.xs(), &[1.0, 0.0, 0.25]);
    assert_eq!(p.score_range(), Some((1.0, 5.0)));
}

#[test]
fn reset_empties_and_bumps_version_but_not_seq() {
    let mut p = Pool::new(3);
    offer(&mut p, 2, 1.0);
    p.apply(&p.plan_reset());
    assert!(p.is_empty());
    assert_eq!(p.version(), 2);
    assert_eq!(p.l_min(), 0);
    offer(&mut p, 2, 1.0);
    assert_eq!(p.seqs(), &[2]);
}

#[test]
fn the_by_step_layout_after_a_change_is_the_one_built_from_scratch() {
    let mut next = xorshift(0x2545_f491_4f6c_dd1d);
    for capacity in [1, 2, 5, 30] {
        let mut p = Pool::new(capacity);
        for _ in 0..200 {
            // Lengths up to 3000 with a few short ones: some pools are too ragged to
            // lay out, and the longest trajectory is sometimes the one replaced.
            let len = if next(4) == 0 {
                1 + next(5)
            } else {
                1 + next(3000)
            } as usize;
            let actions = (0..len).map(|_| next(3) as u32).collect();
            if let Some(c) = p.plan_offer(ActionSeq::Discrete(actions), next(50) as f64) {
                let mut unlaid = p.clone();
                unlaid.apply_without_layout(&c);
                p.apply(&c);
                assert_eq!(
                    (
                        unlaid.version(),
                        unlaid.seqs(),
                        unlaid.lens(),
                        unlaid.l_min()
                    ),
                    (p.version(), p.seqs(), p.lens(), p.l_min())
                );
                assert_eq!((unlaid.xs(), unlaid.by_place()), (p.xs(), p.by_place()));
                assert!(!unlaid.by_step() && unlaid.step_row(0).is_none());
            }
            if next(40) == 0 {
                p.apply(&p.plan_reset());
            }
            let mut fresh = p.clone();
            fresh.build_by_step();
            assert_eq!(p.step_rows, fresh.step_rows);
            assert_eq!(p.by_step, fresh.by_step);
            assert_eq!(p.by_step(), fresh.by_step());
            let mut places: Vec<u32> = p.by_place.clone();
            places.sort_unstable();
            assert!(places.iter().enumerate().all(|(i, &x)| x as usize == i));
            for (place, &i) in p.by_place().iter().enumerate() {
                assert_eq!(p.place_of()[i as usize] as usize, place);
            }
        }
    }
}

#[test]
fn laying_out_several_changes_at_once_gives_the_cells_of_a_full_layout() {
    let mut next = xorshift(0x51af_d7ed_558c_cd1d);
    for capacity in [1, 2, 5, 30] {
        let mut p = Pool::new(capacity);
        for _ in 0..150 {
            let before = p.clone();
            for _ in 0..next(6) {
                if next(25) == 0 {
                    p.apply_without_layout(&p.plan_reset());
                    continue;
                }
                // Mostly alike lengths, sometimes a ragged one (no layout then).
                let len = if next(6) == 0 {
                    1 + next(3000)
                } else {
                    20 + next(10)
                } as usize;
                let actions = (0..len).map(|_| next(3) as u32).collect();
                if let Some(c) = p.plan_offer(ActionSeq::Discrete(actions), next(50) as f64) {
                    p.apply_without_layout(&c);
                }
            }
            p.lay_out_from(&before);
            let mut fresh = p.clone();
            fresh.build_by_step();
            assert_eq!(p.step_rows, fresh.step_rows);
            assert_eq!(p.by_step, fresh.by_step);
        }
    }
}

#[test]
fn restore_rejects_malformed_pools() {
    let t = |seq| Trajectory {
        actions: acts(&[0]),
        score: 0.0,
        seq,
    };
    assert!(Pool::restore(1, vec![t(1), t(2)], 2, 3).is_err());
    assert!(Pool::restore(2, vec![t(1), t(1)], 2, 3).is_err());
    assert!(Pool::restore(2, vec![t(5)], 1, 3).is_err());
    let p = Pool::restore(2, vec![t(2), t(1)], 7, 3).unwrap();
    assert_eq!(p.seqs(), &[1, 2]);
    assert_eq!(p.version(), 7);
}

/// The order an insert derives from the previous one (its sort hint) is the order
/// `Pool::restore` derives from scratch, through inserts, replacements (the worst
/// anywhere in seq order), ties of scores and of normalised scores, and resets; so is the
/// kept score range, and whether the scores differ is read off it.
#[test]
fn the_order_after_a_change_is_the_one_derived_from_scratch() {
    let mut next = xorshift(0x9e37_79b9_7f4a_7c15);
    for capacity in [1, 2, 3, 7, 64] {
        let mut p = Pool::new(capacity);
        for _ in 0..400 {
            // Few distinct scores (ties), some huge ones (normalised ties), some tiny.
            let score = match next(4) {
                0 => next(5) as f64,
                1 => 1e300 * (next(3) as f64 - 1.0),
                2 => 1e-300 * next(7) as f64,
                _ => next(1000) as f64 / 7.0,
            };
            offer(&mut p, 1 + next(4) as usize, score);
            if next(60) == 0 {
                p.apply(&p.plan_reset());
            }
            let trajectories = p
                .trajectories()
                .iter()
                .map(|t| Trajectory::clone(t))
                .collect();
            let fresh = Pool::restore(capacity, trajectories, p.version(), p.next_seq()).unwrap();
            assert_eq!(p.by_place(), fresh.by_place());
            assert_eq!(p.place_of(), fresh.place_of());
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(p.xs()), bits(fresh.xs()));
            let scores = p.trajectories().iter().map(|t| t.score);
            let range = scores.clone().reduce(f64::min).zip(scores.reduce(f64::max));
            assert_eq!(p.score_range(), range);
            assert_eq!(fresh.score_range(), range);
            assert_eq!(p.has_score_spread(), range.is_some_and(|(lo, hi)| lo < hi));
        }
    }
}
