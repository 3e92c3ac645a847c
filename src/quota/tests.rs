use std::sync::atomic::Ordering;

use super::testing::FixedLedger;
use super::*;

fn fixed(tokens: u64) -> (Arc<FixedLedger>, Arc<dyn QuotaLedger>) {
    let f = FixedLedger::with_tokens(tokens);
    (f.clone(), f)
}

#[tokio::test]
async fn steps_come_from_the_ledger_a_block_at_a_time() {
    let (f, ledger) = fixed(1000);
    let blocks = StepBlocks::default();
    // Rate 100: blocks of 10. A batch of 3 takes a block; the next two batches of 3
    // come from it without asking the ledger.
    assert!(blocks.take(&ledger, "t", 100, 3).await.unwrap());
    assert_eq!((f.calls.load(Ordering::Relaxed), blocks.held()), (1, 7));
    for _ in 0..2 {
        assert!(blocks.take(&ledger, "t", 100, 3).await.unwrap());
    }
    assert_eq!((f.calls.load(Ordering::Relaxed), blocks.held()), (1, 1));
    // The fourth needs 2 more: one call, for a block again (1 + 10 - 3 left).
    assert!(blocks.take(&ledger, "t", 100, 3).await.unwrap());
    assert_eq!((f.calls.load(Ordering::Relaxed), blocks.held()), (2, 8));
    assert_eq!(*f.tokens.lock(), 980);
    // A batch larger than a block takes what it misses, and leaves nothing.
    assert!(blocks.take(&ledger, "t", 100, 50).await.unwrap());
    assert_eq!((blocks.held(), *f.tokens.lock()), (0, 938));
}

#[tokio::test]
async fn a_batch_the_ledger_cannot_cover_spends_nothing() {
    let (f, ledger) = fixed(25);
    let blocks = StepBlocks::default();
    assert!(blocks.take(&ledger, "t", 100, 20).await.unwrap());
    assert_eq!((blocks.held(), *f.tokens.lock()), (0, 5));
    // 6 needed, 5 in the ledger: refused, and neither side loses a token.
    assert!(!blocks.take(&ledger, "t", 100, 6).await.unwrap());
    assert_eq!((blocks.held(), *f.tokens.lock()), (0, 5));
    // Less than a block left in the ledger: a batch it covers takes all of it.
    assert!(blocks.take(&ledger, "t", 100, 2).await.unwrap());
    assert_eq!((blocks.held(), *f.tokens.lock()), (3, 0));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 4)]
async fn concurrent_streams_of_a_replica_hold_one_block_at_most() {
    let (_f, ledger) = fixed(1_000_000);
    let blocks = Arc::new(StepBlocks::default());
    let mut tasks = Vec::new();
    for _ in 0..8 {
        let (blocks, ledger) = (blocks.clone(), ledger.clone());
        tasks.push(tokio::spawn(async move {
            for _ in 0..100 {
                assert!(blocks.take(&ledger, "t", 1000, 7).await.unwrap());
                assert!(blocks.held() < block_of(1000), "{}", blocks.held());
            }
        }));
    }
    for t in tasks {
        t.await.unwrap();
    }
    assert_eq!(block_of(5), 1, "at least one token a block");
}

#[tokio::test]
async fn a_ledger_failure_is_the_callers_error() {
    let (f, ledger) = fixed(100);
    f.down.store(true, Ordering::Release);
    let e = StepBlocks::default()
        .take(&ledger, "t", 10, 1)
        .await
        .unwrap_err();
    assert_eq!(e.to_string(), "redis is down");
}
