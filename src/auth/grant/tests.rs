use proptest::prelude::*;

use super::super::{hash_key, Access, Caller};
use super::*;

const KEYS: usize = 3;

/// One key's entry in a key file: `None` (not listed) or (tenant, role).
type Entry = Option<(&'static str, Role)>;

fn key(i: usize) -> String {
    format!("key-{i}")
}

fn write(path: &std::path::Path, entries: &[Entry]) {
    let mut text = String::new();
    for (i, e) in entries.iter().enumerate() {
        if let Some((tenant, role)) = e {
            text += &format!(
                "[[keys]]\ntenant = \"{tenant}\"\nrole = \"{}\"\nsha256 = \"{}\"\n",
                role.as_str(),
                hash_key(key(i).as_bytes())
            );
        }
    }
    std::fs::write(path, text).unwrap();
}

fn shape_caller(access: &Access, i: usize) -> Option<Caller> {
    let path = format!("/{}/Shape", crate::proto::shaping_server::SERVICE_NAME);
    let bearer = format!("Bearer {}", key(i));
    access
        .authorize(&path, Some(bearer.as_bytes()))
        .ok()
        .flatten()
}

fn entry() -> impl Strategy<Value = Entry> {
    prop_oneof![
        Just(None),
        (
            prop_oneof![Just("a"), Just("b")],
            prop_oneof![Just(Role::Reader), Just(Role::Writer), Just(Role::Admin)]
        )
            .prop_map(Some),
    ]
}

#[derive(Debug, Clone)]
enum Op {
    Reload([Entry; KEYS]),
    Open(usize),
}

fn op() -> impl Strategy<Value = Op> {
    prop_oneof![
        [entry(), entry(), entry()].prop_map(Op::Reload),
        (0..KEYS).prop_map(Op::Open),
    ]
}

/// One stream of the model: its key, the tenant it opened as, and how it ended.
struct Open {
    key: usize,
    tenant: &'static str,
    watch: StreamWatch,
    ended: Option<&'static str>,
}

fn code(e: &Error) -> &'static str {
    match e {
        Error::Unauthenticated(_) => "unauthenticated",
        Error::PermissionDenied(_) => "denied",
        Error::ShuttingDown => "shutdown",
        _ => "other",
    }
}

proptest! {
    /// Against the rule written out: a stream ends at the first reload that drops
    /// its key or moves it to another tenant (UNAUTHENTICATED) or gives it a role
    /// below writer (PERMISSION_DENIED), and only then; later reloads never revive it.
    #[test]
    fn streams_end_exactly_when_a_reload_takes_their_key_away(
        first in [entry(), entry(), entry()],
        ops in proptest::collection::vec(op(), 1..24),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("keys.toml");
        write(&path, &first);
        let access = Access::open(&path).unwrap();
        let shutdown = CancellationToken::new();
        let mut table = first;
        let mut streams: Vec<Open> = Vec::new();
        for op in ops {
            match op {
                Op::Open(i) => {
                    let caller = shape_caller(&access, i);
                    let allowed = table[i].filter(|(_, r)| *r >= Role::Writer);
                    prop_assert_eq!(caller.is_some(), allowed.is_some());
                    if let (Some(c), Some((tenant, _))) = (caller, allowed) {
                        let watch = c.watch_stream("Shape", &shutdown);
                        streams.push(Open { key: i, tenant, watch, ended: None });
                    }
                }
                Op::Reload(next) => {
                    write(&path, &next);
                    access.reload().unwrap();
                    table = next;
                    for s in streams.iter_mut().filter(|s| s.ended.is_none()) {
                        s.ended = match table[s.key] {
                            Some((t, _)) if t != s.tenant => Some("unauthenticated"),
                            None => Some("unauthenticated"),
                            Some((_, r)) if r < Role::Writer => Some("denied"),
                            Some(_) => None,
                        };
                        if let Some(want) = s.ended {
                            prop_assert!(s.watch.token.is_cancelled());
                            prop_assert_eq!(code(&s.watch.why()), want);
                        }
                    }
                }
            }
            for s in &streams {
                prop_assert_eq!(s.watch.token.is_cancelled(), s.ended.is_some());
            }
        }
        shutdown.cancel();
        for s in streams.iter().filter(|s| s.ended.is_none()) {
            prop_assert!(s.watch.token.is_cancelled());
            prop_assert_eq!(code(&s.watch.why()), "shutdown");
        }
    }
}

#[test]
fn the_refusal_names_tenant_and_hash_prefix_never_the_key() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("keys.toml");
    write(&path, &[Some(("a", Role::Writer)), None, None]);
    let access = Access::open(&path).unwrap();
    let caller = shape_caller(&access, 0).unwrap();
    let watch = caller.watch_stream("Follow", &CancellationToken::new());
    write(&path, &[Some(("a", Role::Reader)), None, None]);
    access.reload().unwrap();
    let prefix = &hash_key(key(0).as_bytes())[..8];
    let e = watch.why().to_string();
    assert!(e.contains("\"a\"") && e.contains(prefix), "{e}");
    assert!(
        e.contains("role reader") && e.contains("Follow needs role writer"),
        "{e}"
    );
    assert!(!e.contains(&key(0)), "{e}");
    drop(watch);
    assert!(caller
        .grant
        .as_ref()
        .unwrap()
        .streams
        .lock()
        .open
        .is_empty());
}
