use super::*;

fn parse(args: &[&str]) -> ServeArgs {
    let mut full = vec!["tamrm", "serve"];
    full.extend_from_slice(args);
    match Cli::try_parse_from(full).unwrap().command {
        Command::Serve(a) => a,
        _ => unreachable!("parsed a serve command"),
    }
}

/// All layering checks live in one test because they set process environment
/// variables, which no other test reads.
#[test]
fn the_store_url_is_checked() {
    let err = |args: &[&str]| Settings::resolve(&parse(args)).unwrap_err().to_string();
    let s = Settings::resolve(&parse(&["--store", "redis://h:6379/2"])).unwrap();
    assert_eq!(s.store.as_deref(), Some("redis://h:6379/2"));
    assert!(err(&["--store", "redis://h:1", "--data-dir", "/d"]).contains("exclude"));
    let s = Settings::resolve(&parse(&["--store", "rediss://h:6380"])).unwrap();
    assert_eq!(s.store_tls, RedisTls::default(), "the system's roots");
    let bad = err(&["--store", "http://:secret@h:1"]);
    assert!(bad.contains("redis://") && !bad.contains("secret"), "{bad}");
    assert!(err(&["--store", "redis://h:1", "--store-poll-ms", "0"]).contains("store_poll_ms"));
    assert!(err(&["--store", "redis://h:1", "--store-lease-ms", "299"]).contains("store_lease_ms"));
    let cluster = "redis-cluster://:pw@a:7000,b:7001";
    let s = Settings::resolve(&parse(&["--store", cluster])).unwrap();
    assert_eq!(s.store.as_deref(), Some(cluster));
    // TLS files for Redis: with a rediss URL only, a certificate with its key.
    let tls = ["--store-tls-ca", "/ca.pem", "--store-tls-cert", "/c.pem"];
    let s = Settings::resolve(&parse(
        &[
            &["--store", "rediss-cluster://a:1,b:2"][..],
            &tls,
            &["--store-tls-key", "/k.pem"],
        ]
        .concat(),
    ))
    .unwrap();
    assert_eq!(
        s.store_tls,
        RedisTls {
            ca: Some("/ca.pem".into()),
            cert: Some("/c.pem".into()),
            key: Some("/k.pem".into())
        }
    );
    assert!(err(&[&["--store", "rediss://h:1"][..], &tls].concat()).contains("store_tls_key"));
    assert!(err(&[&["--store", "redis://h:1"][..], &tls[..2]].concat()).contains("rediss://"));
    assert!(err(&tls[..2]).contains("need a rediss://"));
    let bad = err(&["--store", "redis-cluster://:secret@a:7000,b"]);
    assert!(
        bad.contains("HOST:PORT") && !bad.contains("secret"),
        "{bad}"
    );
    assert!(err(&["--store", "redis-cluster://a:7000/1"]).contains("database 0"));
}

#[test]
fn defaults_then_file_then_env_then_flags() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("tamrm.toml");
    std::fs::write(
        &file,
        "listen = \"127.0.0.1:7000\"\ndata_dir = \"/from/file\"\nmetrics_listen = \"127.0.0.1:9000\"\nworker_threads = 3\n[limits]\nmax_tasks = 5\nmax_batch_entries = 9\n",
    )
    .unwrap();
    let file_arg = file.to_str().unwrap();

    let s = Settings::resolve(&parse(&[])).unwrap();
    assert_eq!(s, Settings::default());

    let s = Settings::resolve(&parse(&["--config", file_arg])).unwrap();
    assert_eq!(s.listen.port(), 7000);
    assert_eq!(s.metrics_listen.map(|a| a.port()), Some(9000));
    assert_eq!(s.worker_threads, Some(3));
    assert_eq!(s.data_dir.as_deref(), Some(Path::new("/from/file")));
    assert_eq!((s.limits.max_tasks, s.limits.max_batch_entries), (5, 9));
    assert_eq!(
        s.limits.max_envs_per_stream,
        Limits::default().max_envs_per_stream
    );

    std::env::set_var("TAMRM_LISTEN", "127.0.0.1:7001");
    std::env::set_var("TAMRM_MAX_TASKS", "6");
    std::env::set_var("TAMRM_METRICS_LISTEN", "127.0.0.1:9001");
    std::env::set_var("TAMRM_WORKER_THREADS", "2");
    let s = Settings::resolve(&parse(&["--config", file_arg])).unwrap();
    assert_eq!(s.listen.port(), 7001, "env beats file");
    assert_eq!(s.worker_threads, Some(2));
    assert_eq!(s.metrics_listen.map(|a| a.port()), Some(9001));
    assert_eq!(s.limits.max_tasks, 6);
    assert_eq!(
        s.limits.max_batch_entries, 9,
        "file still applies where env is silent"
    );

    let s = Settings::resolve(&parse(&[
        "--config",
        file_arg,
        "--listen",
        "127.0.0.1:0",
        "--max-tasks",
        "7",
        "--metrics-listen",
        "127.0.0.1:9002",
        "--worker-threads",
        "1",
    ]))
    .unwrap();
    assert_eq!(s.listen.port(), 0, "flags beat env");
    assert_eq!(s.worker_threads, Some(1));
    assert_eq!(s.metrics_listen.map(|a| a.port()), Some(9002));
    assert_eq!(s.limits.max_tasks, 7);
    std::env::remove_var("TAMRM_LISTEN");
    std::env::remove_var("TAMRM_MAX_TASKS");
    std::env::remove_var("TAMRM_METRICS_LISTEN");
    std::env::remove_var("TAMRM_WORKER_THREADS");
    // The dashboard is served on the metrics listener: it needs one (here, where no test
    // sets TAMRM_METRICS_LISTEN meanwhile).
    let e = Settings::resolve(&parse(&["--dashboard"]))
        .unwrap_err()
        .to_string();
    assert!(e.contains("--metrics-listen"), "{e}");
    let s = Settings::resolve(&parse(&["--config", file_arg, "--dashboard"])).unwrap();
    assert!(s.dashboard && s.metrics_listen.is_some());
    for bad in ["0", "1025"] {
        let e = Settings::resolve(&parse(&["--worker-threads", bad]))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("worker_threads must be from 1 to 1024"),
            "{bad}: {e}"
        );
    }

    let s = Settings::resolve(&parse(&["--listen", "localhost:7002"])).unwrap();
    assert_eq!(
        s.listen,
        "127.0.0.1:7002".parse().unwrap(),
        "host names resolve"
    );
    for bad in ["http://127.0.0.1:1", "127.0.0.1", "nohost.invalid:1"] {
        let mut full = vec!["tamrm", "serve", "--listen", bad];
        full.truncate(4);
        let e = Cli::try_parse_from(full).unwrap_err().to_string();
        assert!(
            e.contains("host:port") || e.contains("resolve"),
            "{bad}: {e}"
        );
    }

    // TLS files layer like the rest; a certificate without its key is an error.
    std::fs::write(&file, "[tls]\ncert = \"/f/c.pem\"\nkey = \"/f/k.pem\"\n").unwrap();
    let s = Settings::resolve(&parse(&["--config", file_arg])).unwrap();
    assert_eq!(s.tls.key.as_deref(), Some(Path::new("/f/k.pem")));
    std::env::set_var("TAMRM_TLS_KEY", "/env/k.pem");
    let s =
        Settings::resolve(&parse(&["--config", file_arg, "--tls-cert", "/flag/c.pem"])).unwrap();
    std::env::remove_var("TAMRM_TLS_KEY");
    assert_eq!(s.tls.cert.as_deref(), Some(Path::new("/flag/c.pem")));
    assert_eq!(
        s.tls.key.as_deref(),
        Some(Path::new("/env/k.pem")),
        "env beats file"
    );
    let e = Settings::resolve(&parse(&["--tls-cert", "/c.pem"])).unwrap_err();
    assert!(e.to_string().contains("--tls-key"), "{e}");

    std::fs::write(&file, "listn = \"x\"\n").unwrap();
    let e = Settings::resolve(&parse(&["--config", file_arg])).unwrap_err();
    assert!(e.to_string().contains("listn"), "{e}");

    // `tamrm healthcheck` reads the same layers: the file's listen (an unspecified
    // address as loopback) and [tls], its own [healthcheck] table, then env, then flags.
    std::fs::write(
        &file,
        "listen = \"0.0.0.0:7003\"\n[tls]\ncert = \"/f/c.pem\"\nkey = \"/f/k.pem\"\n\
         [healthcheck]\ntls_server_name = \"file-name\"\ntls_ca = \"/f/ca.pem\"\n",
    )
    .unwrap();
    let check = |args: &[&str]| {
        let full = [&["tamrm", "healthcheck"][..], args].concat();
        match Cli::try_parse_from(full).unwrap().command {
            Command::Healthcheck(h) => h.resolve(),
            _ => unreachable!("parsed a healthcheck command"),
        }
    };
    let t = check(&["--config", file_arg]).unwrap();
    assert_eq!(t.addr, "127.0.0.1:7003".parse().unwrap());
    assert_eq!(t.server_tls.cert.as_deref(), Some(Path::new("/f/c.pem")));
    assert_eq!(t.tls.tls_server_name.as_deref(), Some("file-name"));
    assert_eq!(t.tls.tls_ca.as_deref(), Some(Path::new("/f/ca.pem")));
    std::env::set_var("TAMRM_LISTEN", "127.0.0.1:7004");
    std::env::set_var("TAMRM_TLS_SERVER_NAME", "env-name");
    let t = check(&["--config", file_arg, "--tls-ca", "/flag/ca.pem"]).unwrap();
    assert_eq!(t.addr.port(), 7004, "env beats file");
    assert_eq!(t.tls.tls_server_name.as_deref(), Some("env-name"));
    assert_eq!(t.tls.tls_ca.as_deref(), Some(Path::new("/flag/ca.pem")));
    let t = check(&["--config", file_arg, "--addr", "127.0.0.1:7005"]).unwrap();
    assert_eq!(t.addr.port(), 7005, "flags beat env");
    std::env::remove_var("TAMRM_LISTEN");
    std::env::remove_var("TAMRM_TLS_SERVER_NAME");
    std::fs::write(&file, "[healthcheck]\ntls_cert = \"x\"\n").unwrap();
    let e = check(&["--config", file_arg]).unwrap_err();
    assert!(e.to_string().contains("tls_cert"), "{e}");
}
