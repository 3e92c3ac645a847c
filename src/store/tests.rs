use super::*;

#[test]
fn apply_ops_follows_the_update_rule_in_order() {
    let base = Pool::new(1);
    let offer = |score| PoolOp::Offer {
        actions: ActionSeq::Discrete(vec![0]),
        score,
        end: None,
    };
    let (pool, changed) = apply_ops(&base, vec![offer(1.0), offer(1.0), offer(2.0)]);
    assert_eq!(changed, vec![true, false, true]);
    assert_eq!(pool.version(), 2);
    assert_eq!(pool.seqs(), &[2]);
    let (pool, changed) = apply_ops(&pool, vec![PoolOp::Reset]);
    assert_eq!((changed, pool.len(), pool.version()), (vec![true], 0, 3));
    assert_eq!(base.version(), 0, "the base is not touched");
}

/// Laid out once at the end, a group's pool is the pool of its changes applied one by
/// one, layout by step included.
#[test]
fn apply_ops_lays_out_once_what_one_by_one_lays_out_each_time() {
    let mut state = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = |m: u64| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state % m
    };
    for capacity in [1, 3, 8, 40] {
        let mut pool = Pool::new(capacity);
        for _ in 0..60 {
            let ops: Vec<PoolOp> = (0..next(6))
                .map(|_| match next(12) {
                    0 => PoolOp::Reset,
                    _ => PoolOp::Offer {
                        actions: ActionSeq::Discrete(
                            (0..1 + next(40)).map(|_| next(3) as u32).collect(),
                        ),
                        score: next(5) as f64,
                        end: None,
                    },
                })
                .collect();
            let (grouped, changed) = apply_ops(&pool, ops.clone());
            let mut one_by_one = pool.clone();
            let mut each = Vec::new();
            for op in ops {
                let (p, c) = apply_ops(&one_by_one, vec![op]);
                one_by_one = p;
                each.extend(c);
            }
            assert_eq!(changed, each);
            assert_eq!(
                (grouped.version(), grouped.next_seq(), grouped.seqs()),
                (
                    one_by_one.version(),
                    one_by_one.next_seq(),
                    one_by_one.seqs()
                )
            );
            assert_eq!(
                (grouped.xs(), grouped.lens()),
                (one_by_one.xs(), one_by_one.lens())
            );
            assert_eq!(grouped.by_step(), one_by_one.by_step());
            for t in 0..=grouped.lens().iter().copied().max().unwrap_or(0) {
                assert_eq!(grouped.step_row(t), one_by_one.step_row(t), "row {t}");
            }
            pool = grouped;
        }
    }
}
