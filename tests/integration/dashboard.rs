//! The dashboard (`tamrm serve --dashboard`) on a real server's metrics listener: loaded
//! by a real browser (Debian's `chromium-headless-shell`), its answers to keys of each
//! tenant and role, and a task that does not exist.

use std::process::Command;

use crate::common::{add, connect, create, discrete, dtraj, start_server, with_key};
use crate::metrics::http_get;
use tamrm::proto;

const BROWSER: &str = "chromium-headless-shell";

/// The browser's arguments for a headless run as root in a container.
fn browser(args: &[&str]) -> Option<std::process::Output> {
    let out = Command::new(BROWSER)
        .args(["--no-sandbox", "--disable-gpu", "--hide-scrollbars"])
        .args(args)
        .output();
    match out {
        Ok(o) => Some(o),
        Err(e) => {
            eprintln!("SKIPPED: {BROWSER} cannot run ({e}); Debian: apt-get install chromium-headless-shell (.ci/run installs it)");
            None
        }
    }
}

/// `GET path` with headers: (status, body).
async fn get_with(addr: std::net::SocketAddr, path: &str, header: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut conn = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\n{header}Connection: close\r\n\r\n");
    conn.write_all(req.as_bytes()).await.unwrap();
    let mut raw = String::new();
    conn.read_to_string(&mut raw).await.unwrap();
    let (head, body) = raw.split_once("\r\n\r\n").unwrap();
    (
        head.split(' ').nth(1).unwrap().parse().unwrap(),
        body.to_string(),
    )
}

#[tokio::test(flavor = "multi_thread")]
async fn a_browser_shows_the_tasks_and_a_pool_of_bars_that_refreshes() {
    let server = start_server(None, |s| {
        s.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
        s.dashboard = true;
    })
    .await;
    let page = server.metrics_addr().unwrap();
    let mut c = connect(server.addr()).await;
    create(&mut c, "maze", discrete(5, 40, 3, 0, 1)).await;
    create(&mut c, "cart/pole", discrete(2, 8, 2, 0, 1)).await;
    for i in 0..30u32 {
        let actions: Vec<u32> = (0..(5 + i * 7 % 60)).map(|j| (i + j / 3) % 5).collect();
        add(
            &mut c,
            "maze",
            dtraj(&actions, f64::from(i * 37 % 23) - 4.5),
        )
        .await;
    }
    let version = 30;
    let (status, _) = http_get(page, "/task?id=nope").await;
    assert_eq!(status, 404);
    let Some(out) =
        tokio::task::spawn_blocking(move || browser(&["--dump-dom", &format!("http://{page}/")]))
            .await
            .unwrap()
    else {
        return;
    };
    let dom = String::from_utf8_lossy(&out.stdout).into_owned();
    assert!(
        dom.contains(r#"data-task="maze""#) && dom.contains(r#"data-task="cart/pole""#),
        "{dom}"
    );
    let url = format!("http://{page}/task?id=maze");
    let u = url.clone();
    let out = tokio::task::spawn_blocking(move || browser(&["--dump-dom", &u]).unwrap())
        .await
        .unwrap();
    let dom = String::from_utf8_lossy(&out.stdout).into_owned();
    assert_eq!(dom.matches(r#"<rect class="score""#).count(), 30, "{dom}");
    assert!(
        dom.contains(&format!(r#"<span class="version">{version}</span>"#)),
        "{dom}"
    );
    // A change shows up without a reload: the page's script polls its fragment.
    add(&mut c, "maze", dtraj(&[1, 2, 3], 99.0)).await;
    let u = url.clone();
    let out = tokio::task::spawn_blocking(move || {
        browser(&["--virtual-time-budget=5000", "--dump-dom", &u]).unwrap()
    })
    .await
    .unwrap();
    let dom = String::from_utf8_lossy(&out.stdout).into_owned();
    assert_eq!(dom.matches(r#"<rect class="score""#).count(), 31, "{dom}");
    // The screenshot the docs show (kept in docs/img/ with TAMRM_UPDATE_SCREENSHOT=1).
    let dir = tempfile::tempdir().unwrap();
    let shot = dir.path().join("dashboard.png");
    let arg = format!("--screenshot={}", shot.display());
    let out = tokio::task::spawn_blocking(move || {
        browser(&["--window-size=1280,900", &arg, &url]).unwrap()
    })
    .await
    .unwrap();
    let png = std::fs::read(&shot).unwrap_or_else(|e| {
        panic!(
            "no screenshot ({e}): {}",
            String::from_utf8_lossy(&out.stderr)
        )
    });
    assert_eq!(&png[1..4], b"PNG");
    if std::env::var_os("TAMRM_UPDATE_SCREENSHOT").is_some() {
        let docs = concat!(env!("CARGO_MANIFEST_DIR"), "/docs/img/dashboard.png");
        std::fs::write(docs, &png).unwrap();
    }
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn with_api_keys_the_page_needs_a_reader_key_and_shows_only_its_tenant() {
    let dir = tempfile::tempdir().unwrap();
    let keys = dir.path().join("keys.toml");
    let entry = |tenant: &str, role: &str, key: &str| {
        format!(
            "[[keys]]\ntenant = \"{tenant}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n",
            tamrm::auth::hash_key(key.as_bytes())
        )
    };
    std::fs::write(
        &keys,
        entry("a", "writer", "a-writer")
            + &entry("a", "reader", "a-reader")
            + &entry("b", "writer", "b-writer"),
    )
    .unwrap();
    let server = start_server(None, |s| {
        s.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
        s.dashboard = true;
        s.api_keys = Some(keys);
    })
    .await;
    let page = server.metrics_addr().unwrap();
    let mut c = connect(server.addr()).await;
    for (key, id) in [("a-writer", "mine"), ("b-writer", "theirs")] {
        c.create_task(with_key(
            Some(key),
            proto::CreateTaskRequest {
                task_id: id.into(),
                config: Some(discrete(3, 4, 1, 0, 1)),
            },
        ))
        .await
        .unwrap();
    }
    let (status, body) = http_get(page, "/").await;
    assert_eq!(status, 401, "{body}");
    assert!(body.contains("reader role"), "{body}");
    assert_eq!(http_get(page, "/?key=wrong").await.0, 401);
    let (status, body) = http_get(page, "/?key=a-reader").await;
    assert_eq!(status, 200, "{body}");
    assert!(
        body.contains(r#"data-task="mine""#) && !body.contains("theirs"),
        "{body}"
    );
    assert!(
        body.contains("/task?id=mine&amp;key=a-reader"),
        "links carry the key: {body}"
    );
    let (status, body) = get_with(
        page,
        "/fragment/tasks",
        "Authorization: Bearer b-writer\r\n",
    )
    .await;
    assert_eq!(status, 200);
    assert!(body.contains("theirs") && !body.contains("mine"), "{body}");
    // Another tenant's task is not there for this key.
    assert_eq!(http_get(page, "/task?id=theirs&key=a-reader").await.0, 404);
    assert_eq!(http_get(page, "/task?id=mine&key=a-reader").await.0, 200);
    // The metrics stay where they were, without a key.
    assert_eq!(http_get(page, "/metrics").await.0, 200);
    server.shutdown().await;
}

#[tokio::test(flavor = "multi_thread")]
async fn without_dashboard_the_page_is_not_served() {
    let server = start_server(None, |s| {
        s.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    })
    .await;
    assert_eq!(http_get(server.metrics_addr().unwrap(), "/").await.0, 404);
    server.shutdown().await;
}
