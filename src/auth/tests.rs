use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use super::usage::Bucket;
use super::*;

fn path(method: &str) -> String {
    format!("/{}/{method}", crate::proto::shaping_server::SERVICE_NAME)
}

fn bearer_of(key: &str) -> Vec<u8> {
    format!("Bearer {key}").into_bytes()
}

/// A key file with one key per (tenant, role) given, key = "<tenant>-<role>".
fn file(entries: &[(&str, &str)], extra: &str) -> (tempfile::TempDir, Access) {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("keys.toml");
    std::fs::write(&p, text(entries, extra)).unwrap();
    let access = Access::open(&p).unwrap();
    (dir, access)
}

fn text(entries: &[(&str, &str)], extra: &str) -> String {
    let mut t = String::new();
    for (tenant, role) in entries {
        t += &format!(
            "[[keys]]\ntenant = \"{tenant}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n",
            hash_key(format!("{tenant}-{role}").as_bytes())
        );
    }
    t + extra
}

fn code(r: Result<Option<Caller>, Error>) -> &'static str {
    match r {
        Ok(Some(_)) => "ok",
        Ok(None) => "free",
        Err(Error::Unauthenticated(_)) => "unauthenticated",
        Err(Error::PermissionDenied(_)) => "denied",
        Err(_) => "other",
    }
}

#[test]
fn every_role_against_every_rpc() {
    let (_d, a) = file(&[("t", "reader"), ("t", "writer"), ("t", "admin")], "");
    for (method, needed) in SHAPING_ROLES {
        for role in [Role::Reader, Role::Writer, Role::Admin] {
            let key = bearer_of(&format!("t-{}", role.as_str()));
            let got = a.authorize(&path(method), Some(&key));
            let want = if role >= *needed { "ok" } else { "denied" };
            assert_eq!(code(got), want, "{method} with {role:?}");
        }
        assert_eq!(code(a.authorize(&path(method), None)), "unauthenticated");
        let unknown = bearer_of("t-root");
        assert_eq!(
            code(a.authorize(&path(method), Some(&unknown))),
            "unauthenticated"
        );
    }
    let ok = a
        .authorize(&path("GetTask"), Some(&bearer_of("t-admin")))
        .unwrap()
        .unwrap();
    assert_eq!((ok.tenant(), ok.role()), ("t", Role::Admin));
}

#[test]
fn health_is_free_reflection_and_unknown_paths_need_a_key() {
    let (_d, a) = file(&[("t", "reader")], "");
    assert_eq!(
        code(a.authorize("/grpc.health.v1.Health/Check", None)),
        "free"
    );
    assert_eq!(
        code(a.authorize("/grpc.health.v1.Health/Watch", None)),
        "free"
    );
    let reflection = "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo";
    assert_eq!(code(a.authorize(reflection, None)), "unauthenticated");
    assert_eq!(
        code(a.authorize(reflection, Some(&bearer_of("t-reader")))),
        "ok"
    );
    assert_eq!(code(a.authorize("/x.Y/Z", None)), "unauthenticated");
    assert_eq!(code(a.authorize("garbage", None)), "unauthenticated");
    assert_eq!(needed_role(&path("NoSuchRpc")), Some(Role::Reader));
    assert_eq!(needed_role(&path("DeleteTask")), Some(Role::Admin));
}

#[test]
fn the_bearer_scheme_is_required_and_case_insensitive() {
    let (_d, a) = file(&[("t", "writer")], "");
    let p = path("GetTask");
    for ok in ["Bearer t-writer", "bearer t-writer", "BEARER  t-writer "] {
        assert_eq!(code(a.authorize(&p, Some(ok.as_bytes()))), "ok", "{ok:?}");
    }
    for bad in [
        "t-writer",
        "Basic t-writer",
        "Bearer",
        "Bearer    ",
        "",
        "Bearer\u{0}",
    ] {
        let got = a.authorize(&p, Some(bad.as_bytes()));
        assert_eq!(code(got), "unauthenticated", "{bad:?}");
    }
    // The hash of the key is compared, not a prefix of it.
    assert_eq!(
        code(a.authorize(&p, Some(b"Bearer t-write"))),
        "unauthenticated"
    );
}

#[test]
fn refusals_never_echo_the_key() {
    let (_d, a) = file(&[("t", "reader")], "");
    for key in ["sekrit-value", "t-reader"] {
        let e = a
            .authorize(&path("DeleteTask"), Some(&bearer_of(key)))
            .unwrap_err();
        assert!(!e.to_string().contains(key), "{e}");
    }
}

#[tokio::test]
async fn reload_swaps_keys_and_quotas_and_keeps_usage() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("keys.toml");
    std::fs::write(
        &p,
        text(&[("t", "writer")], "[tenants.t]\nmax_open_streams = 1\n"),
    )
    .unwrap();
    let a = Access::open(&p).unwrap();
    let old = bearer_of("t-writer");
    let caller = a.authorize(&path("Shape"), Some(&old)).unwrap().unwrap();
    let slot = caller.open_stream().await.unwrap();
    assert!(matches!(
        caller.open_stream().await,
        Err(Error::ResourceExhausted(m)) if m.contains("max_open_streams = 1")
    ));

    // A broken file leaves the keys in force.
    std::fs::write(&p, "[[keys]]\ntenant = 1\n").unwrap();
    assert!(a.reload().unwrap_err().to_string().contains("keys.toml"));
    assert_eq!(code(a.authorize(&path("Shape"), Some(&old))), "ok");

    std::fs::write(
        &p,
        text(&[("t", "admin")], "[tenants.t]\nmax_open_streams = 2\n"),
    )
    .unwrap();
    assert_eq!(a.reload().unwrap(), (1, 1));
    assert_eq!(
        code(a.authorize(&path("Shape"), Some(&old))),
        "unauthenticated"
    );
    let new = a
        .authorize(&path("Shape"), Some(&bearer_of("t-admin")))
        .unwrap()
        .unwrap();
    // The slot taken before the reload still counts: one more fits, not two.
    let second = new.open_stream().await.unwrap();
    assert!(new.open_stream().await.is_err());
    drop(slot);
    let third = caller.open_stream().await.unwrap();
    drop((second, third));
    assert_eq!(caller.tenant.open_streams.load(Ordering::Acquire), 0);
}

#[tokio::test]
async fn tenants_have_their_own_usage() {
    let (_d, a) = file(
        &[("a", "writer"), ("b", "writer")],
        "[tenants.a]\nmax_open_streams = 1\n[tenants.b]\nmax_open_streams = 1\nmax_tasks = 4\n",
    );
    let ca = a
        .authorize(&path("Shape"), Some(&bearer_of("a-writer")))
        .unwrap()
        .unwrap();
    let cb = a
        .authorize(&path("Shape"), Some(&bearer_of("b-writer")))
        .unwrap()
        .unwrap();
    let _sa = ca.open_stream().await.unwrap();
    let _sb = cb.open_stream().await.unwrap();
    assert!(ca.open_stream().await.is_err() && cb.open_stream().await.is_err());
    assert_eq!((ca.max_tasks(), cb.max_tasks()), (None, Some(4)));
    assert!(Caller::open().open_stream().await.is_ok());
}

#[test]
fn the_step_bucket_holds_one_second_and_refills() {
    let t0 = Instant::now();
    let mut b = Bucket {
        tokens: 10.0,
        at: t0,
    };
    assert!(b.take(10, 10, t0));
    assert!(!b.take(1, 10, t0), "empty");
    assert!(
        !b.take(6, 10, t0 + Duration::from_millis(500)),
        "5 refilled"
    );
    assert!(b.take(5, 10, t0 + Duration::from_millis(500)));
    // Never more than one second's worth, however long it rested.
    assert!(!b.take(11, 10, t0 + Duration::from_secs(60)));
    assert!(b.take(10, 10, t0 + Duration::from_secs(60)));
    // A clock that goes backwards refills nothing.
    assert!(!b.take(1, 10, t0));
}

#[tokio::test]
async fn step_quota_errors_say_why() {
    let (_d, a) = file(
        &[("s", "writer")],
        "[tenants.s]\nmax_steps_per_second = 100\n",
    );
    let c = a
        .authorize(&path("Shape"), Some(&bearer_of("s-writer")))
        .unwrap()
        .unwrap();
    let e = c.take_steps(101).await.unwrap_err().to_string();
    assert!(e.contains("can never fit") && e.contains("100"), "{e}");
    c.take_steps(100).await.unwrap();
    let e = c.take_steps(100).await.unwrap_err().to_string();
    assert!(e.contains("max_steps_per_second = 100"), "{e}");
    Caller::open().take_steps(usize::MAX).await.unwrap();
}

#[test]
fn new_keys_are_random_and_hash_as_documented() {
    let (a, b) = (new_key().unwrap(), new_key().unwrap());
    assert_ne!(a, b);
    assert!(a.starts_with("tamrm_") && a.len() == 6 + 64, "{a}");
    assert_eq!(
        hash_key(b"test"),
        "9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"
    );
}

#[tokio::test]
async fn with_a_shared_ledger_the_quotas_hold_over_replicas() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("keys.toml");
    let quotas = "[tenants.t]\nmax_open_streams = 1\nmax_steps_per_second = 100\n";
    std::fs::write(&p, text(&[("t", "writer")], quotas)).unwrap();
    // Shared by two Accesses as by two replicas.
    let shared = crate::quota::testing::FixedLedger::with_tokens(150);
    let ledger: Arc<dyn QuotaLedger> = shared.clone();
    let replica = || {
        Access::open_with(&p, Some(ledger.clone()))
            .unwrap()
            .authorize(&path("Shape"), Some(&bearer_of("t-writer")))
            .unwrap()
            .unwrap()
    };
    let (a, b) = (replica(), replica());
    let slot = a.open_stream().await.unwrap();
    let e = b.open_stream().await.unwrap_err();
    assert!(
        matches!(&e, Error::ResourceExhausted(m) if m.contains("max_open_streams = 1")),
        "{e:?}"
    );
    assert_eq!(a.tenant.open_streams.load(Ordering::Acquire), 0, "a lease");
    drop(slot);
    let _slot = b.open_stream().await.unwrap();

    // 150 tokens for both: A takes a block of 10 for 5, B takes 140 in batches of 70.
    a.take_steps(5).await.unwrap();
    b.take_steps(70).await.unwrap();
    b.take_steps(70).await.unwrap();
    let e = b.take_steps(1).await.unwrap_err().to_string();
    assert!(e.contains("max_steps_per_second = 100"), "{e}");
    // A spends what it holds, and no more.
    a.take_steps(5).await.unwrap();
    assert!(a.take_steps(1).await.is_err());

    // A ledger that cannot answer: UNAVAILABLE naming the quota; nothing is let through.
    shared.down.store(true, Ordering::Release);
    let e = replica().open_stream().await.unwrap_err();
    assert!(
        matches!(&e, Error::StoreUnavailable(m) if m.contains("max_open_streams") && m.contains("redis is down")),
        "{e:?}"
    );
    let e = a.take_steps(1).await.unwrap_err();
    assert!(
        matches!(&e, Error::StoreUnavailable(m) if m.contains("max_steps_per_second")),
        "{e:?}"
    );
}
