//! The pool gauges and `process_*` metrics on a real server's metrics endpoint: their
//! values, `promtool check metrics` on the exposition, and every metric the Grafana
//! dashboard (docker/grafana/tamrm-dashboard.json) queries being served.

use std::collections::BTreeSet;

use crate::common::{add, batch, connect, create, discrete, dtraj, start_server, Stream};
use crate::metrics::{scrape, Metrics};
use tamrm::proto;

/// A server with metrics on, two tasks with pools, and a Shape stream that ran.
async fn busy_server() -> (tamrm::server::RunningServer, Metrics) {
    let server = start_server(None, |s| {
        s.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    })
    .await;
    let mut c = connect(server.addr()).await;
    create(&mut c, "a", discrete(3, 4, 1, 0, 1)).await;
    create(&mut c, "empty", discrete(3, 4, 1, 0, 1)).await;
    for (actions, score) in [(&[0, 1][..], 2.5), (&[2][..], -1.25), (&[1, 1, 1][..], 9.0)] {
        add(&mut c, "a", dtraj(actions, score)).await;
    }
    let (mut s, _) = Stream::open(&mut c, "a", 2).await.unwrap();
    s.step(batch(&[0, 1], &[1.0, 2.0], &[true, false]))
        .await
        .unwrap();
    drop(s.close());
    c.get_task(proto::GetTaskRequest {
        task_id: "nope".into(),
    })
    .await
    .unwrap_err();
    let m = scrape(server.metrics_addr().unwrap()).await;
    (server, m)
}

#[tokio::test(flavor = "multi_thread")]
async fn pool_gauges_and_process_metrics_are_served() {
    let (server, m) = busy_server().await;
    assert_eq!(
        m.value("tamrm_pool_size", &[("task", "a")]),
        4.0,
        "3 added, 1 episode"
    );
    assert_eq!(m.value("tamrm_pool_best_score", &[("task", "a")]), 9.0);
    assert_eq!(m.value("tamrm_pool_worst_score", &[("task", "a")]), -1.25);
    assert_eq!(m.value("tamrm_pool_size", &[("task", "empty")]), 0.0);
    assert_eq!(m.get("tamrm_pool_best_score", &[("task", "empty")]), None);
    assert!(m.value("process_resident_memory_bytes", &[]) > 1e6);
    assert!(m.value("process_open_fds", &[]) >= 3.0);
    assert!(m.value("process_cpu_seconds_total", &[]) > 0.0);
    let start = m.value("process_start_time_seconds", &[]);
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    assert!(
        start <= now + 1.0 && start > now - 86_400.0,
        "{start} vs {now}"
    );
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn promtool_accepts_the_exposition() {
    let (server, m) = busy_server().await;
    server.shutdown().await;
    let Ok(mut child) = std::process::Command::new("promtool")
        .args(["check", "metrics"])
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
    else {
        eprintln!(
            "SKIPPED promtool_accepts_the_exposition: promtool is not on the PATH (Debian: apt-get install prometheus; .ci/run installs it)"
        );
        return;
    };
    use std::io::Write;
    child
        .stdin
        .take()
        .unwrap()
        .write_all(m.0.as_bytes())
        .unwrap();
    let out = child.wait_with_output().unwrap();
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        out.status.success(),
        "promtool check metrics: {said}\n{}",
        m.0
    );
    // Lint findings (names, units, help) are printed but do not fail the exit status.
    assert!(
        said.trim().is_empty(),
        "promtool check metrics found: {said}"
    );
}

/// The metric names a PromQL expression uses (identifiers followed by `{` or `[`, or
/// standing alone, that start with a served prefix).
fn metric_names(expr: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    let bytes: Vec<char> = expr.chars().collect();
    let mut i = 0;
    while i < bytes.len() {
        if bytes[i].is_ascii_alphabetic() || bytes[i] == '_' {
            let start = i;
            while i < bytes.len() && (bytes[i].is_ascii_alphanumeric() || bytes[i] == '_') {
                i += 1;
            }
            let word: String = bytes[start..i].iter().collect();
            if ["tamrm_", "grpc_server_", "process_"]
                .iter()
                .any(|p| word.starts_with(p))
            {
                out.insert(word);
            }
        } else {
            i += 1;
        }
    }
    out
}

/// Every sample name and every `# TYPE` name of an exposition.
fn served(text: &str) -> BTreeSet<String> {
    text.lines()
        .filter_map(|l| match l.strip_prefix("# TYPE ") {
            Some(rest) => rest.split(' ').next(),
            None if l.starts_with('#') => None,
            None => l.split(['{', ' ']).next(),
        })
        .map(str::to_string)
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn every_metric_the_dashboard_queries_is_served() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docker/grafana/tamrm-dashboard.json"
    );
    let dashboard: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    let mut exprs = Vec::new();
    fn walk(v: &serde_json::Value, out: &mut Vec<String>) {
        match v {
            serde_json::Value::Object(o) => {
                for (k, v) in o {
                    match (k.as_str(), v) {
                        ("expr" | "definition", serde_json::Value::String(s)) => {
                            out.push(s.clone())
                        }
                        _ => walk(v, out),
                    }
                }
            }
            serde_json::Value::Array(a) => a.iter().for_each(|v| walk(v, out)),
            _ => {}
        }
    }
    walk(&dashboard, &mut exprs);
    let wanted: BTreeSet<String> = exprs.iter().flat_map(|e| metric_names(e)).collect();
    for name in [
        "tamrm_pool_size",
        "tamrm_pool_best_score",
        "process_open_fds",
    ] {
        assert!(
            wanted.contains(name),
            "the dashboard does not query {name}: {wanted:?}"
        );
    }
    let (server, m) = busy_server().await;
    server.shutdown().await;
    let served = served(&m.0);
    let missing: Vec<&String> = wanted
        .iter()
        .filter(|name| !served.contains(*name))
        .collect();
    assert!(
        missing.is_empty(),
        "the dashboard queries metrics the server does not serve: {missing:?}\nserved: {served:?}"
    );
}
