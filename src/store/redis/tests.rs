use super::codec::score_text;
use super::keys::Keys;
use super::url::{redact, RedisTarget};

#[test]
fn passwords_are_not_shown() {
    assert_eq!(redact("redis://:s3cret@h:6379/0"), "redis://***@h:6379/0");
    assert_eq!(redact("redis://h:6379"), "redis://h:6379");
}

#[test]
fn store_urls_name_one_server_or_the_seed_nodes_of_a_cluster() {
    assert_eq!(
        RedisTarget::parse("redis://:pw@h:6379/2"),
        Ok(RedisTarget::Node("redis://:pw@h:6379/2".into()))
    );
    assert_eq!(
        RedisTarget::parse("redis-cluster://u:pw@a:7000,b:7001/"),
        Ok(RedisTarget::Cluster(vec![
            "redis://u:pw@a:7000".into(),
            "redis://u:pw@b:7001".into()
        ]))
    );
    assert_eq!(
        RedisTarget::parse("redis-cluster://[::1]:7000"),
        Ok(RedisTarget::Cluster(vec!["redis://[::1]:7000".into()]))
    );
    // TLS: the same forms with rediss, every node of a cluster over TLS.
    let node = RedisTarget::parse("rediss://:pw@h:6380/1").unwrap();
    assert_eq!(node, RedisTarget::Node("rediss://:pw@h:6380/1".into()));
    let cluster = RedisTarget::parse("rediss-cluster://u:pw@a:7000,b:7001").unwrap();
    assert_eq!(
        cluster,
        RedisTarget::Cluster(vec![
            "rediss://u:pw@a:7000".into(),
            "rediss://u:pw@b:7001".into()
        ])
    );
    assert!(node.tls() && cluster.tls());
    for plain in ["redis://h:1", "redis-cluster://a:1,b:2"] {
        assert!(!RedisTarget::parse(plain).unwrap().tls(), "{plain}");
    }
    for bad in [
        "redis://",
        "redis-cluster://",
        "redis-cluster://a:7000,,b:7001",
        "redis-cluster://a",
        "redis-cluster://a:port",
        "redis-cluster://:7000",
        "redis-cluster://a:7000/3",
        "redis-cluster://a:7000?x=1",
        "rediss://",
        "rediss-cluster://a",
        "rediss-cluster://a:1/2",
        "redis-clusters://a:1",
        "http://:pw@h:1",
    ] {
        let e = RedisTarget::parse(bad).unwrap_err();
        assert!(!e.contains("pw"), "{bad}: {e}");
    }
}

#[test]
fn scores_are_written_as_lua_reads_them_back() {
    for s in [0.1, -0.0, 1e-300, f64::MAX, -123.456, 5e-324] {
        let text = score_text(s);
        assert_eq!(
            text.parse::<f64>().unwrap().to_bits(),
            s.to_bits(),
            "{text}"
        );
    }
}

#[test]
fn keys_of_a_task_share_its_hash_tag() {
    let k = Keys::of("acme@cart");
    for key in [
        &k.meta,
        &k.traj,
        &k.scores,
        &Keys::ended("acme@cart", "i", "c"),
    ] {
        assert!(key.contains("{acme@cart}"), "{key}");
    }
}
