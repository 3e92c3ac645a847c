//! The `tamrm` binary's commands other than `serve`: `tamrm healthcheck` against a real
//! server on 127.0.0.1:0, serving, shut down, and never there.

use crate::common::*;

use std::process::Command;

fn healthcheck(args: &[&str]) -> (bool, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_tamrm"))
        .arg("healthcheck")
        .args(args)
        .env_remove("TAMRM_LISTEN")
        .output()
        .expect("run tamrm healthcheck");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[tokio::test(flavor = "multi_thread")]
async fn healthcheck_exits_0_only_while_the_server_serves() {
    let server = start_server(None, |_| {}).await;
    let addr = server.addr().to_string();
    let a = addr.clone();
    let (ok, err) = tokio::task::spawn_blocking(move || healthcheck(&["--addr", &a]))
        .await
        .unwrap();
    assert!(ok, "serving server reported unhealthy: {err}");
    server.shutdown().await;
    let a = addr.clone();
    let (ok, err) =
        tokio::task::spawn_blocking(move || healthcheck(&["--addr", &a, "--timeout-secs", "2"]))
            .await
            .unwrap();
    assert!(!ok, "a stopped server reported healthy");
    assert!(err.contains("unhealthy") && err.contains(&addr), "{err}");
}

#[test]
fn healthcheck_rejects_a_malformed_address() {
    let (ok, err) = healthcheck(&["--addr", "http://127.0.0.1:1"]);
    assert!(!ok);
    assert!(err.contains("host:port"), "{err}");
}

fn tamrm_key(args: &[&str], stdin: &str) -> (bool, String, String) {
    use std::io::Write;
    let mut child = Command::new(env!("CARGO_BIN_EXE_tamrm"))
        .arg("key")
        .args(args)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("run tamrm key");
    child
        .stdin
        .take()
        .unwrap()
        .write_all(stdin.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// `tamrm key` prints a new key once and a key-file entry that holds only its hash, and
/// a server with that file takes the key (health checks need none).
#[tokio::test(flavor = "multi_thread")]
async fn tamrm_key_makes_a_key_file_entry_the_server_accepts() {
    let (ok, out, err) = tamrm_key(&["--tenant", "team-a", "--role", "reader"], "");
    assert!(ok, "{err}");
    let key = out
        .lines()
        .find_map(|l| l.strip_prefix("# key: "))
        .expect("the key is printed")
        .to_string();
    let file = tamrm::auth::KeyFile::parse(&out).expect("the output is a key file");
    assert_eq!(file.keys.len(), 1);
    assert_eq!(file.keys[0].tenant, "team-a");
    assert_eq!(file.keys[0].role, tamrm::auth::Role::Reader);
    let entry = out
        .lines()
        .filter(|l| !l.starts_with('#'))
        .collect::<Vec<_>>()
        .join("\n");
    assert!(!entry.contains(&key), "the entry holds the key in clear");
    let (_, again, _) = tamrm_key(&[], "");
    assert!(!again.contains(&key), "two keys are the same");

    // A given key is hashed, not printed.
    let (ok, out, _) = tamrm_key(&["--stdin", "--role", "admin"], "test\n");
    assert!(ok);
    assert!(out.contains("9f86d081884c7d659a2feaa0c55ad015a3bf4f1b2b0b822cd15d6c15b0f00a08"));
    assert!(!out.contains("# key"));
    let (ok, _, err) = tamrm_key(&["--tenant", "a@b"], "");
    assert!(!ok && err.contains("--tenant"), "{err}");

    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("keys.toml");
    let (_, entry, _) = tamrm_key(&["--stdin", "--tenant", "team-a"], &key);
    std::fs::write(&path, entry).unwrap();
    let server = start_server(None, |s| s.api_keys = Some(path)).await;
    let mut c = connect(server.addr()).await;
    let mut req = tonic::Request::new(tamrm::proto::ListTasksRequest {});
    req.metadata_mut()
        .insert("authorization", format!("Bearer {key}").parse().unwrap());
    c.list_tasks(req).await.expect("the key is accepted");
    let no_key = c
        .list_tasks(tamrm::proto::ListTasksRequest {})
        .await
        .unwrap_err();
    assert_eq!(no_key.code(), tonic::Code::Unauthenticated);
    let a = server.addr().to_string();
    let (ok, err) = tokio::task::spawn_blocking(move || healthcheck(&["--addr", &a]))
        .await
        .unwrap();
    assert!(ok, "the health check needs no key: {err}");
    server.shutdown().await;
}
