//! A data dir written by the previous on-disk format starts under this build and restores
//! exactly what the release that wrote it restored from it.
//!
//! `tests/fixtures/format2/data` was written by the last release of format 2 (snapshots,
//! then a commit log of pool changes and episode ends past them, left by a kill -9 with a
//! torn last group appended), and `expected.bin` holds what that release served after
//! starting over it: every task (`ListTasksResponse`) and every pool (`Pool`), each
//! length-delimited. `write_format2_fixture` made both; it is kept (ignored) as the record
//! of how, and only means something when run by a format-2 build.

use std::path::{Path, PathBuf};

use prost::Message;
use tamrm::proto::{self, shape_request, StepBatch};

use crate::common::*;
use crate::durability::{assert_bit_exact, assert_configs_bit_exact, copy_dir, populate, snapshot};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/format2")
}

fn encode_state(tasks: &[proto::Task], pools: &[proto::Pool]) -> Vec<u8> {
    let mut b = Vec::new();
    proto::ListTasksResponse {
        tasks: tasks.to_vec(),
    }
    .encode_length_delimited(&mut b)
    .unwrap();
    for p in pools {
        p.encode_length_delimited(&mut b).unwrap();
    }
    b
}

fn decode_state(mut b: &[u8]) -> (Vec<proto::Task>, Vec<proto::Pool>) {
    let tasks = proto::ListTasksResponse::decode_length_delimited(&mut b)
        .unwrap()
        .tasks;
    let mut pools = Vec::new();
    while !b.is_empty() {
        pools.push(proto::Pool::decode_length_delimited(&mut b).unwrap());
    }
    (tasks, pools)
}

/// A stream of a named client: its episode ends are recorded (SPEC §9).
async fn named_stream(c: &mut Client, task: &str, client: &str) -> Stream {
    let mut s = Stream::raw(c).await.unwrap();
    s.send(proto::ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: task.into(),
            num_envs: 2,
            client_id: client.into(),
            ..Default::default()
        })),
    })
    .await;
    s.recv().await.unwrap().expect("opened");
    s
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "writes tests/fixtures/format2; meaningful only when run by a format-2 build"]
async fn write_format2_fixture() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let arg = data.to_str().unwrap();
    // Snapshots: a varied state, stopped gracefully.
    let bin = Binary::start(&["--data-dir", arg]);
    let mut c = connect(bin.addr).await;
    populate(&mut c).await;
    drop(c);
    assert!(bin.terminate().0.success());
    // Then changes in the log only: inserts and replacements, episode ends of a named
    // client, a task created after the snapshots, a deleted task; killed.
    let bin = Binary::start(&["--data-dir", arg]);
    let mut c = connect(bin.addr).await;
    let mut s = named_stream(&mut c, "d", "client-a").await;
    for i in 0..6u32 {
        s.step(StepBatch {
            env_ids: vec![0, 1, 0, 1],
            actions: vec![i % 4, 3, (i + 1) % 4, i % 2],
            rewards: vec![2.0, f64::from(i), 3.5, -1.0],
            terminated: vec![false, false, true, i % 2 == 0],
            ..Default::default()
        })
        .await
        .unwrap();
    }
    drop(s);
    add(&mut c, "c/1:x", ctraj(&[0.25, -0.5, 8.0], 7.0)).await;
    create(&mut c, "late", discrete(3, 3, 2, 0, 1)).await;
    add(&mut c, "late", dtraj(&[2, 1], 0.5)).await;
    add(&mut c, "late", dtraj(&[0, 0, 1], 1.5)).await;
    c.delete_task(proto::DeleteTaskRequest {
        task_id: "x/y".into(),
    })
    .await
    .unwrap();
    wait_open_streams(&mut c, "d", 0).await;
    drop(c);
    drop(bin); // SIGKILL
               // A torn last group: its magic and a length, then nothing.
    let log = data.join("commits.log");
    let mut bytes = std::fs::read(&log).unwrap();
    bytes.extend_from_slice(b"TGRP\x40\x00\x00\x00\x01");
    std::fs::write(&log, bytes).unwrap();
    std::fs::remove_file(data.join("LOCK")).ok();

    let out = fixture();
    let _ = std::fs::remove_dir_all(&out);
    copy_dir(&data, &out.join("data"));
    let bin = Binary::start(&["--data-dir", arg]);
    let mut c = connect(bin.addr).await;
    let (tasks, pools) = snapshot(&mut c).await;
    std::fs::write(out.join("expected.bin"), encode_state(&tasks, &pools)).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_format2_data_dir_restores_what_its_release_restored() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    copy_dir(&fixture().join("data"), &data);
    // Git keeps no empty directory: the `traj/` of a task whose snapshot lists nothing
    // is made again, as the release that wrote the fixture had it.
    for task in std::fs::read_dir(data.join("tasks")).unwrap() {
        std::fs::create_dir_all(task.unwrap().path().join("traj")).unwrap();
    }
    let (mut tasks, pools) = decode_state(&std::fs::read(fixture().join("expected.bin")).unwrap());
    // The release that wrote the fixture predates SPEC v1.3's require_score_spread: its
    // task files lack the field, which this build reads as false and reports.
    for t in &mut tasks {
        let config = t.config.as_mut().unwrap();
        assert_eq!(config.require_score_spread, None, "{}", t.task_id);
        config.require_score_spread = Some(false);
    }
    assert!(tasks.iter().any(|t| t.task_id == "late"));
    assert!(!tasks.iter().any(|t| t.task_id == "x/y"));
    let arg = data.to_str().unwrap();
    let bin = Binary::start(&["--data-dir", arg]);
    let mut c = connect(bin.addr).await;
    let (t, p) = snapshot(&mut c).await;
    assert_eq!(t, tasks);
    assert_configs_bit_exact(&tasks, &t);
    assert_bit_exact(&pools, &p);
    // It goes on: a change, a graceful stop and a start keep it.
    let r = add(&mut c, "late", dtraj(&[1, 1, 1], 9.0)).await;
    assert!(r.inserted);
    let (tasks, pools) = snapshot(&mut c).await;
    drop(c);
    let (status, stderr) = bin.terminate();
    assert!(status.success(), "{stderr}");
    let marker: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data.join("tamrm.json")).unwrap()).unwrap();
    assert_eq!(marker["format"], tamrm::store::FORMAT_VERSION);
    let bin = Binary::start(&["--data-dir", arg]);
    let mut c = connect(bin.addr).await;
    let (t, p) = snapshot(&mut c).await;
    assert_eq!(t, tasks);
    assert_bit_exact(&pools, &p);
    // `tamrm compact` refuses a data dir in use, and folds a stopped server's log into
    // the snapshots (the way back to a format-2 build), keeping everything.
    let compact = || {
        std::process::Command::new(env!("CARGO_BIN_EXE_tamrm"))
            .args(["compact", "--data-dir", arg])
            .output()
            .unwrap()
    };
    let busy = compact();
    assert!(!busy.status.success());
    assert!(String::from_utf8_lossy(&busy.stderr).contains("in use"));
    drop(c);
    assert!(bin.terminate().0.success());
    let log = data.join("commits.log");
    assert!(
        std::fs::metadata(&log).unwrap().len() > 44,
        "a stop keeps the log"
    );
    let done = compact();
    assert!(done.status.success(), "{done:?}");
    assert_eq!(
        std::fs::metadata(&log).unwrap().len(),
        44,
        "compacted: the header alone"
    );
    let bin = Binary::start(&["--data-dir", arg]);
    let mut c = connect(bin.addr).await;
    let (t, p) = snapshot(&mut c).await;
    assert_eq!(t, tasks);
    assert_bit_exact(&pools, &p);
    drop(c);
    assert!(bin.terminate().0.success());
}
