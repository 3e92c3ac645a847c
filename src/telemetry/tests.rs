use super::*;

#[test]
fn task_labels_are_capped_and_stable() {
    let labels = TaskLabels::new(2);
    let name = |t: &str| labels.label(t).task.to_string();
    assert_eq!(name("a"), "a");
    assert_eq!(name("b"), "b");
    assert_eq!(name("c"), OTHER_TASKS, "past the cap");
    assert_eq!(name("a"), "a", "a named task keeps its label");
    assert_eq!(name("d"), OTHER_TASKS);
    assert_eq!(labels.named.lock().len(), 2);
}

#[test]
fn series_past_the_cap_share_one_label() {
    let m = Metrics::with_task_labels(3);
    for i in 0..50 {
        m.shape(&format!("task-{i}"))
            .batch(2, 1, Duration::from_micros(7));
    }
    let registry = crate::registry::Registry::open(
        Arc::new(crate::store::MemoryStore::new()),
        crate::limits::Limits::default(),
    );
    let registry = futures::executor::block_on(registry).unwrap().0;
    let text = m.render(&registry).unwrap();
    let series: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("tamrm_steps_shaped_total{"))
        .collect();
    assert_eq!(series.len(), 4, "3 named tasks and the rest: {series:?}");
    assert!(
        text.contains("tamrm_steps_shaped_total{task=\"~other\"} 94\n"),
        "{text}"
    );
    assert!(text.contains("tamrm_episodes_completed_total{task=\"task-0\"} 1\n"));
    assert!(text.contains("tamrm_batch_entries_count 50\n"), "{text}");
    assert!(
        text.contains("tamrm_batch_seconds_bucket{le=\"1e-05\"} 50\n"),
        "{text}"
    );
    assert!(text.contains("tamrm_tasks 0\n"));
    assert!(text.contains("tamrm_open_streams 0\n"), "streams closed");
    assert!(text.contains("tamrm_stream_bytes_reserved 0\n"), "{text}");
    let open = m.shape("task-0");
    let reserved = registry.reserve_stream_bytes(1234).unwrap();
    let text = m.render(&registry).unwrap();
    assert!(text.contains("tamrm_open_streams 1\n"), "{text}");
    assert!(
        text.contains("tamrm_stream_bytes_reserved 1234\n"),
        "{text}"
    );
    drop((open, reserved));
}

#[test]
fn pool_gauges_follow_the_tasks_and_share_one_series_past_the_cap() {
    use crate::core::{ActionSeq, TaskConfigInput};
    let m = Metrics::with_task_labels(2);
    let registry = crate::registry::Registry::open(
        Arc::new(crate::store::MemoryStore::new()),
        crate::limits::Limits::default(),
    );
    let registry = futures::executor::block_on(registry).unwrap().0;
    let config = TaskConfigInput {
        num_actions: 2,
        ..Default::default()
    };
    let scores: [&[f64]; 5] = [&[1.0, 2.0], &[3.0, 5.0], &[-1.0, 0.5], &[], &[7.0]];
    futures::executor::block_on(async {
        for (i, scores) in scores.iter().enumerate() {
            let t = registry
                .create("default", &format!("t{i}"), &config, None)
                .await
                .unwrap();
            for s in *scores {
                t.offer(ActionSeq::Discrete(vec![0, 1]), *s).await.unwrap();
            }
        }
    });
    let text = m.render(&registry).unwrap();
    let has = |line: &str| text.lines().any(|l| l == line);
    assert!(has("tamrm_pool_size{task=\"t0\"} 2"), "{text}");
    assert!(has("tamrm_pool_best_score{task=\"t1\"} 5.0"), "{text}");
    assert!(has("tamrm_pool_worst_score{task=\"t1\"} 3.0"), "{text}");
    // t2, t3 and t4 share ~other: sizes summed, the best best and the worst worst; an
    // empty pool adds no score.
    assert!(has("tamrm_pool_size{task=\"~other\"} 3"), "{text}");
    assert!(has("tamrm_pool_best_score{task=\"~other\"} 7.0"), "{text}");
    assert!(
        has("tamrm_pool_worst_score{task=\"~other\"} -1.0"),
        "{text}"
    );
    assert_eq!(text.matches("tamrm_pool_size{").count(), 3, "{text}");
    // A deleted task's series go.
    futures::executor::block_on(registry.delete("default", "t1")).unwrap();
    let text = m.render(&registry).unwrap();
    assert!(!text.contains("task=\"t1\""), "{text}");
    assert!(text.contains("tamrm_pool_size{task=\"t0\"} 2\n"), "{text}");
}

#[test]
fn process_metrics_are_read_from_proc() {
    let r = process::read().expect("/proc is there on Linux");
    assert!(r.resident_bytes > 1 << 20, "{r:?}");
    assert!(r.open_fds >= 3, "{r:?}");
    let now = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_secs_f64();
    assert!(
        r.start_time > now - 86_400.0 && r.start_time <= now + 1.0,
        "{r:?}"
    );
    // A command name with spaces and parentheses does not shift the fields.
    let stat = "42 (a (b) c) S 1 42 42 0 -1 4194560 100 0 0 0 250 50 0 0 20 0 3 0 1000 1 2";
    let r = process::parse(
        stat,
        "cpu 1\nbtime 1700000000\n",
        "VmRSS:\t  2048 kB\n",
        100.0,
        7,
    )
    .unwrap();
    assert_eq!(r.cpu_seconds, 3.0);
    assert_eq!(r.start_time, 1_700_000_010.0);
    assert_eq!(r.resident_bytes, 2048 * 1024);
    assert_eq!(r.open_fds, 7);
    assert!(process::parse("garbage", "", "", 100.0, 0).is_none());
}
