//! Prometheus metrics end to end: a real server on 127.0.0.1:0 with `/metrics` on its own
//! port, real RPCs, and the counters read back over HTTP.

use crate::common::{batch, connect, create, discrete, get_task, start_server, Stream};
use tamrm::proto;
use tokio::io::{AsyncReadExt, AsyncWriteExt};

/// `GET path` over a fresh HTTP/1.1 connection: (status code, body).
pub(crate) async fn http_get(addr: std::net::SocketAddr, path: &str) -> (u16, String) {
    let mut conn = tokio::net::TcpStream::connect(addr).await.unwrap();
    let req = format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n");
    conn.write_all(req.as_bytes()).await.unwrap();
    let mut raw = String::new();
    conn.read_to_string(&mut raw).await.unwrap();
    let (head, body) = raw.split_once("\r\n\r\n").expect("an HTTP response");
    let status = head
        .split(' ')
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no status line: {head}"));
    (status, body.to_string())
}

/// The exposition of the server's metrics endpoint.
pub(crate) async fn scrape(addr: std::net::SocketAddr) -> Metrics {
    let (status, body) = http_get(addr, "/metrics").await;
    assert_eq!(status, 200, "{body}");
    Metrics(body)
}

pub(crate) struct Metrics(pub(crate) String);

impl Metrics {
    /// The value of the sample `name` whose labels are exactly `labels`; `None` if there
    /// is no such series.
    pub(crate) fn get(&self, name: &str, labels: &[(&str, &str)]) -> Option<f64> {
        self.0.lines().find_map(|line| {
            let (series, value) = line.rsplit_once(' ')?;
            let (n, rest) = match series.split_once('{') {
                Some((n, rest)) => (n, rest.strip_suffix('}')?),
                None => (series, ""),
            };
            let mut got: Vec<&str> = rest.split(',').filter(|l| !l.is_empty()).collect();
            let mut want: Vec<String> =
                labels.iter().map(|(k, v)| format!("{k}=\"{v}\"")).collect();
            got.sort_unstable();
            want.sort_unstable();
            (n == name && got == want).then(|| value.parse().unwrap())
        })
    }

    /// Like [`Metrics::get`], but the series must exist.
    #[track_caller]
    pub(crate) fn value(&self, name: &str, labels: &[(&str, &str)]) -> f64 {
        self.get(name, labels)
            .unwrap_or_else(|| panic!("no series {name}{labels:?} in:\n{}", self.0))
    }

    /// `grpc_server_*` labels of a method.
    fn rpc<'a>(kind: &'a str, service: &'a str, method: &'a str) -> Vec<(&'a str, &'a str)> {
        vec![
            ("grpc_type", kind),
            ("grpc_service", service),
            ("grpc_method", method),
        ]
    }

    /// (`grpc_server_msg_received_total`, `grpc_server_msg_sent_total`) of a method.
    #[track_caller]
    fn messages(&self, kind: &str, service: &str, method: &str) -> (f64, f64) {
        let labels = Metrics::rpc(kind, service, method);
        (
            self.value("grpc_server_msg_received_total", &labels),
            self.value("grpc_server_msg_sent_total", &labels),
        )
    }

    #[track_caller]
    fn handled(&self, kind: &str, service: &str, method: &str, code: &str) -> f64 {
        let mut labels = Metrics::rpc(kind, service, method);
        labels.push(("grpc_code", code));
        self.value("grpc_server_handled_total", &labels)
    }
}

const SHAPING: &str = "tamrm.v1.Shaping";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn rpcs_and_shaping_move_the_counters() {
    let server = start_server(None, |s| {
        s.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    })
    .await;
    let maddr = server.metrics_addr().expect("metrics are on");
    assert_ne!(maddr.port(), 0);
    assert_eq!(http_get(maddr, "/").await.0, 404);
    let m = scrape(maddr).await;
    assert_eq!(m.value("tamrm_tasks", &[]), 0.0);
    assert_eq!(m.value("tamrm_open_streams", &[]), 0.0);
    let format = tamrm::build_info::DATA_DIR_FORMAT.to_string();
    let build = [
        ("version", env!("CARGO_PKG_VERSION")),
        ("commit", tamrm::build_info::COMMIT),
        ("proto", tamrm::build_info::PROTO),
        ("data_dir_format", format.as_str()),
    ];
    assert_eq!(m.value("tamrm_build_info", &build), 1.0);

    let mut c = connect(server.addr()).await;
    create(&mut c, "m", discrete(3, 8, 2, 0, 1)).await;
    get_task(&mut c, "m").await;
    let missing = c
        .get_task(proto::GetTaskRequest {
            task_id: "nope".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(missing.code(), tonic::Code::NotFound);

    let m = scrape(maddr).await;
    assert_eq!(m.value("tamrm_tasks", &[]), 1.0);
    let get = Metrics::rpc("unary", SHAPING, "GetTask");
    assert_eq!(m.value("grpc_server_started_total", &get), 2.0);
    assert_eq!(m.handled("unary", SHAPING, "GetTask", "OK"), 1.0);
    assert_eq!(m.handled("unary", SHAPING, "GetTask", "NotFound"), 1.0);
    assert_eq!(m.handled("unary", SHAPING, "CreateTask", "OK"), 1.0);
    assert_eq!(m.value("grpc_server_handling_seconds_count", &get), 2.0);
    assert_eq!(
        m.messages("unary", SHAPING, "GetTask"),
        (2.0, 1.0),
        "a failed call answers with trailers only"
    );

    // A Shape stream: 3 batches of 2 envs, 3 episode ends over 2 batches.
    let shape = Metrics::rpc("bidi_stream", SHAPING, "Shape");
    let (mut s, _) = Stream::open(&mut c, "m", 2).await.unwrap();
    s.step(batch(&[0, 1], &[1.0, 1.0], &[false, false]))
        .await
        .unwrap();
    s.step(batch(&[1, 2], &[1.0, 1.0], &[true, true]))
        .await
        .unwrap();
    s.step(batch(&[2, 0], &[1.0, 1.0], &[true, false]))
        .await
        .unwrap();

    let m = scrape(maddr).await;
    assert_eq!(m.value("grpc_server_started_total", &shape), 1.0);
    assert_eq!(
        m.get("grpc_server_handling_seconds_count", &shape),
        None,
        "an open stream is not handled yet"
    );
    assert_eq!(m.value("tamrm_open_streams", &[]), 1.0);
    assert_eq!(
        m.value("tamrm_stream_bytes_reserved", &[]),
        (2 * (100_000 * 4 + 8 * 24) + tamrm::service::STREAM_WINDOW as usize) as f64,
        "2 envs of the default max_trajectory_len on a pool of 8, and the stream's window"
    );
    assert_eq!(
        m.messages("bidi_stream", SHAPING, "Shape"),
        (4.0, 4.0),
        "Open and 3 batches, opened and 3 shaped"
    );
    let task = [("task", "m")];
    assert_eq!(m.value("tamrm_steps_shaped_total", &task), 6.0);
    assert_eq!(m.value("tamrm_episodes_completed_total", &task), 3.0);
    assert_eq!(m.value("tamrm_pool_changes_total", &task), 3.0);
    assert_eq!(m.value("tamrm_batch_entries_count", &[]), 3.0);
    assert_eq!(m.value("tamrm_batch_entries_sum", &[]), 6.0);
    assert_eq!(m.value("tamrm_batch_seconds_count", &[]), 3.0);
    assert_eq!(
        m.value("tamrm_store_commit_seconds_count", &[]),
        2.0,
        "one commit per batch with episode ends"
    );

    let mut rx = s.close();
    assert!(rx.message().await.unwrap().is_none());
    let m = scrape(maddr).await;
    assert_eq!(m.handled("bidi_stream", SHAPING, "Shape", "OK"), 1.0);
    assert_eq!(m.value("grpc_server_handling_seconds_count", &shape), 1.0);
    assert_eq!(m.value("tamrm_open_streams", &[]), 0.0);
    assert_eq!(m.value("tamrm_stream_bytes_reserved", &[]), 0.0);

    // A stream that fails after its headers went out ends with the status in its trailers.
    let err = Stream::open(&mut c, "nope", 1).await.err().unwrap();
    assert_eq!(err.code(), tonic::Code::NotFound);
    // Paths the server does not serve share one `unknown` series.
    for path in ["/no.Such/Method", "/tamrm.v1.Shaping/Nope"] {
        let mut grpc = tonic::client::Grpc::new(
            tonic::transport::Channel::from_shared(format!("http://{}", server.addr()))
                .unwrap()
                .connect()
                .await
                .unwrap(),
        );
        grpc.ready().await.unwrap();
        let codec = tonic_prost::ProstCodec::<(), ()>::default();
        let path = http::uri::PathAndQuery::from_static(path);
        let status = grpc
            .unary(tonic::Request::new(()), path, codec)
            .await
            .unwrap_err();
        assert_eq!(status.code(), tonic::Code::Unimplemented);
    }
    let m = scrape(maddr).await;
    assert_eq!(m.handled("bidi_stream", SHAPING, "Shape", "NotFound"), 1.0);
    let unknown = Metrics::rpc("unknown", "unknown", "unknown");
    assert_eq!(m.value("grpc_server_started_total", &unknown), 2.0);
    assert_eq!(
        m.handled("unknown", "unknown", "unknown", "Unimplemented"),
        2.0
    );
    assert_eq!(m.value("tamrm_steps_shaped_total", &task), 6.0);

    // A stream the client drops is handled once the server ends it: as Canceled when the
    // reset arrives first, as OK when the server sees the half-close first (a race the
    // client decides, not the server).
    let shape_codes = |m: &Metrics| {
        ["OK", "Canceled"].map(|code| {
            let mut labels = Metrics::rpc("bidi_stream", SHAPING, "Shape");
            labels.push(("grpc_code", code));
            m.get("grpc_server_handled_total", &labels).unwrap_or(0.0)
        })
    };
    let before = shape_codes(&scrape(maddr).await);
    let (mut s, _) = Stream::open(&mut c, "m", 1).await.unwrap();
    s.step(batch(&[0], &[1.0], &[false])).await.unwrap();
    drop(s);
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(30);
    loop {
        let m = scrape(maddr).await;
        let after = shape_codes(&m);
        if after[0] + after[1] == before[0] + before[1] + 1.0
            && m.value("tamrm_open_streams", &[]) == 0.0
        {
            assert_eq!(m.value("tamrm_steps_shaped_total", &task), 7.0);
            break;
        }
        assert!(
            std::time::Instant::now() < deadline,
            "the dropped stream is not handled:\n{}",
            m.0
        );
        tokio::time::sleep(std::time::Duration::from_millis(20)).await;
    }
    server.shutdown().await;
}

/// `grpc_server_msg_received_total` / `grpc_server_msg_sent_total`: one each per unary
/// call, one per message each way on a stream, whatever the size of the messages (the batches
/// here take more than one HTTP/2 frame each way).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_are_counted_per_method() {
    let server = start_server(None, |s| {
        s.metrics_listen = Some("127.0.0.1:0".parse().unwrap());
    })
    .await;
    let maddr = server.metrics_addr().expect("metrics are on");
    let mut c = connect(server.addr()).await;
    let config = proto::TaskConfig {
        max_trajectory_len: Some(64),
        ..discrete(3, 8, 2, 0, 1)
    };
    create(&mut c, "msgs", config).await;
    let m = scrape(maddr).await;
    assert_eq!(m.messages("unary", SHAPING, "CreateTask"), (1.0, 1.0));
    assert_eq!(
        m.get(
            "grpc_server_msg_received_total",
            &Metrics::rpc("unary", SHAPING, "GetTask")
        ),
        None,
        "a method not called yet has no series"
    );

    const N: usize = 5;
    const ENVS: usize = 2_000; // a batch of ≈ 20 kB, a shaped batch of ≈ 50 kB: several frames
    let (mut s, _) = Stream::open(&mut c, "msgs", ENVS as u32).await.unwrap();
    for i in 0..N {
        let actions: Vec<u32> = (0..ENVS).map(|e| ((e + i) % 3) as u32).collect();
        let shaped = s
            .step(batch(&actions, &[0.5; ENVS], &[false; ENVS]))
            .await
            .unwrap();
        assert_eq!(shaped.rewards.len(), ENVS);
    }
    let want = (N + 1) as f64;
    let m = scrape(maddr).await;
    assert_eq!(
        m.messages("bidi_stream", SHAPING, "Shape"),
        (want, want),
        "Open and {N} batches in, opened and {N} shaped out"
    );
    let mut rx = s.close();
    assert!(rx.message().await.unwrap().is_none());
    let m = scrape(maddr).await;
    assert_eq!(m.handled("bidi_stream", SHAPING, "Shape", "OK"), 1.0);
    assert_eq!(
        m.messages("bidi_stream", SHAPING, "Shape"),
        (want, want),
        "the half-close and the trailers are no messages"
    );
    assert_eq!(m.messages("unary", SHAPING, "CreateTask"), (1.0, 1.0));
    server.shutdown().await;
}

#[tokio::test]
async fn metrics_are_off_by_default() {
    let server = start_server(None, |_| {}).await;
    assert_eq!(server.metrics_addr(), None);
    server.shutdown().await;
}
