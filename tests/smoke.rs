mod common;
use common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn smoke() {
    let server = start_server(None, |_| {}).await;
    let mut c = connect(server.addr()).await;
    let t = create(&mut c, "t1", discrete(2, 2, 2, 0, 1)).await;
    assert_eq!(t.config.unwrap().pool_capacity, Some(2));
    let (mut s, _) = Stream::open(&mut c, "t1", 2).await.unwrap();
    let out = s
        .step(batch(&[0, 1], &[1.0, 1.0], &[true, false]))
        .await
        .unwrap();
    assert_eq!(out.pool_version, 1);
    let out = s
        .step(batch(&[0, 1], &[1.0, 1.0], &[false, false]))
        .await
        .unwrap();
    assert_eq!(
        out.knn_active,
        vec![true, false],
        "env 1 is at t = 1 = L_min"
    );
    assert_eq!(out.steps, vec![0, 1]);
    server.shutdown().await;
}
