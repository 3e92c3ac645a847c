//! The `tamrm` binary's commands other than `serve`: `tamrm healthcheck` against a real
//! server on 127.0.0.1:0, serving, shut down, and never there.

mod common;
use common::*;

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
