//! The seed corpora (`fuzz/corpus/<target>/seed-*`): the requests of the test suites
//! (tests/integration/bad_input.rs, tests/integration/server.rs, the session tests) in the
//! targets' input formats, valid ones and ones each rule of SPEC §8 refuses, and for the
//! disk target every file of a real data dir. A target started with
//! `TAMRM_FUZZ_SEEDS=DIR` writes its seeds there (fuzz/run.sh does, when a corpus is
//! missing).

use std::path::Path;

use prost::Message;
use tamrm::proto::{self, shape_request, ShapeRequest, StepBatch};

use crate::join_chunks;
use crate::targets::{disk_template, UNARY};

fn open(task: &str, num_envs: u32) -> Vec<u8> {
    ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: task.into(),
            num_envs,
            ..Default::default()
        })),
    }
    .encode_to_vec()
}

fn resumed(task: &str) -> Vec<u8> {
    ShapeRequest {
        kind: Some(shape_request::Kind::Open(proto::Open {
            task_id: task.into(),
            num_envs: 2,
            client_id: "seed-client".into(),
            resume: vec![proto::EnvResume {
                env_id: 1,
                actions: vec![2, 1],
                reward_sum: 3.0,
                episode: 4,
                ..Default::default()
            }],
        })),
    }
    .encode_to_vec()
}

fn steps(b: StepBatch) -> Vec<u8> {
    ShapeRequest {
        kind: Some(shape_request::Kind::Steps(b)),
    }
    .encode_to_vec()
}

fn discrete(actions: &[u32], rewards: &[f64], ends: &[bool]) -> StepBatch {
    StepBatch {
        env_ids: (0..actions.len() as u32).collect(),
        actions: actions.to_vec(),
        rewards: rewards.to_vec(),
        terminated: ends.to_vec(),
        ..Default::default()
    }
}

fn write(dir: &Path, name: &str, bytes: &[u8]) {
    std::fs::create_dir_all(dir).expect("mkdir");
    std::fs::write(dir.join(name), bytes).expect("write seed");
}

fn shape_seeds() -> Vec<Vec<Vec<u8>>> {
    let episode: Vec<Vec<u8>> = (0..8u32)
        .map(|t| {
            steps(discrete(
                &[t % 3, (t + 1) % 3],
                &[1.0, f64::from(t)],
                &[t % 3 == 2, t == 7],
            ))
        })
        .collect();
    let mut runs = vec![
        [vec![open("d", 2)], episode.clone()].concat(),
        [vec![resumed("d")], episode.clone()].concat(),
        vec![
            open("c", 1),
            steps(StepBatch {
                env_ids: vec![0],
                action_vectors: vec![0.5, -1.0],
                rewards: vec![2.0],
                terminated: vec![true],
                ..Default::default()
            }),
        ],
        vec![
            open("g", 2),
            steps(StepBatch {
                env_ids: vec![0, 1],
                actions: vec![3, 0],
                rewards: vec![1.0, 1.0],
                values: vec![0.5, 0.25],
                next_values: vec![0.75, 0.5],
                truncated: vec![false, true],
                ..Default::default()
            }),
            steps(StepBatch {
                env_ids: vec![0],
                actions: vec![1],
                rewards: vec![1.0],
                q_values: vec![0.1, 0.2, 0.3, 0.4],
                next_q_values: vec![0.4, 0.3, 0.2, 0.1],
                terminated: vec![true],
                episode_scores: [(0, 9.5)].into_iter().collect(),
                ..Default::default()
            }),
            steps(StepBatch {
                abandon: vec![1],
                ..Default::default()
            }),
        ],
    ];
    // Refused ones (SPEC §8): steps first, an unknown task, a second open, an action out
    // of range, a non-finite reward, mismatched lengths, an env twice, undecodable bytes.
    runs.push(vec![steps(discrete(&[0], &[1.0], &[false]))]);
    runs.push(vec![open("nope", 1)]);
    runs.push(vec![open("d", 0)]);
    runs.push(vec![open("d", 1), open("d", 1)]);
    runs.push(vec![open("d", 1), steps(discrete(&[7], &[1.0], &[false]))]);
    runs.push(vec![
        open("d", 1),
        steps(discrete(&[0], &[f64::NAN], &[false])),
    ]);
    runs.push(vec![
        open("d", 2),
        steps(discrete(&[0, 1], &[1.0], &[false, true])),
    ]);
    runs.push(vec![
        open("d", 2),
        steps(StepBatch {
            env_ids: vec![1, 1],
            actions: vec![0, 0],
            rewards: vec![1.0, 1.0],
            ..Default::default()
        }),
    ]);
    runs.push(vec![open("d", 1), vec![0x0a, 0xff, 0xff]]);
    runs
}

fn unary_seeds() -> Vec<Vec<Vec<u8>>> {
    let call = |method: &str, msg: Vec<u8>| {
        let i = UNARY.iter().position(|m| *m == method).expect("a method") as u8;
        [vec![i], msg].concat()
    };
    let create = |id: &str, config: proto::TaskConfig| {
        call(
            "CreateTask",
            proto::CreateTaskRequest {
                task_id: id.into(),
                config: Some(config),
            }
            .encode_to_vec(),
        )
    };
    let add = |id: &str, t: proto::Trajectory| {
        call(
            "AddTrajectory",
            proto::AddTrajectoryRequest {
                task_id: id.into(),
                trajectory: Some(t),
            }
            .encode_to_vec(),
        )
    };
    let task = |method: &str, id: &str| {
        let msg = match method {
            "GetTask" => proto::GetTaskRequest { task_id: id.into() }.encode_to_vec(),
            "DeleteTask" => proto::DeleteTaskRequest { task_id: id.into() }.encode_to_vec(),
            "ResetPool" => proto::ResetPoolRequest { task_id: id.into() }.encode_to_vec(),
            _ => proto::GetPoolRequest { task_id: id.into() }.encode_to_vec(),
        };
        call(method, msg)
    };
    let traj = |actions: Vec<u32>, score: f64| proto::Trajectory {
        actions,
        score,
        ..Default::default()
    };
    vec![
        vec![
            create(
                "new",
                proto::TaskConfig {
                    num_actions: 5,
                    pool_capacity: Some(2),
                    ..Default::default()
                },
            ),
            add("new", traj(vec![1, 4, 0], 3.0)),
            add("new", traj(vec![2], 1.0)),
            add("new", traj(vec![3, 3], 2.0)),
            task("GetPool", "new"),
            task("ResetPool", "new"),
            task("DeleteTask", "new"),
            task("GetTask", "new"),
        ],
        vec![
            call("ListTasks", proto::ListTasksRequest {}.encode_to_vec()),
            add(
                "c",
                proto::Trajectory {
                    action_vectors: vec![0.5, 0.25, -1.0, 2.0],
                    score: 4.0,
                    ..Default::default()
                },
            ),
            task("GetPool", "c"),
        ],
        // Refused: a bad config, a config that differs, a non-finite score, an action out
        // of range, an empty trajectory, a bad task id, undecodable bytes.
        vec![create(
            "bad",
            proto::TaskConfig {
                num_actions: 3,
                action_dim: 2,
                ..Default::default()
            },
        )],
        vec![create(
            "d",
            proto::TaskConfig {
                num_actions: 4,
                ..Default::default()
            },
        )],
        vec![add("d", traj(vec![1], f64::INFINITY))],
        vec![add("d", traj(vec![9], 1.0))],
        vec![add("d", traj(vec![], 1.0))],
        vec![task("GetTask", "no spaces allowed")],
        vec![call("GetPool", vec![0x0a, 0x05, b'd'])],
    ]
}

/// Writes `target`'s seeds into `dir` if `TAMRM_FUZZ_SEEDS` names it.
pub fn write_if_asked(target: &str) {
    let Some(dir) = std::env::var_os("TAMRM_FUZZ_SEEDS") else {
        return;
    };
    let dir = Path::new(&dir);
    let seeds: Vec<Vec<u8>> = match target {
        "shape_stream" => shape_seeds().iter().map(|r| join_chunks(r)).collect(),
        "unary" => unary_seeds().iter().map(|r| join_chunks(r)).collect(),
        _ => disk_template()
            .iter()
            .enumerate()
            .map(|(i, (_, bytes))| [&[i as u8], &bytes[..]].concat())
            .collect(),
    };
    for (i, s) in seeds.iter().enumerate() {
        write(dir, &format!("seed-{i:02}"), s);
    }
    eprintln!(
        "{} seeds of {target} written to {}",
        seeds.len(),
        dir.display()
    );
}
