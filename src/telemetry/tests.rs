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
