//! The dashboard's page of one task (`tamrm serve --dashboard`, `/task?id=ID`), rendered
//! server-side (docs/benchmarks.md, "Dashboard page").
//!
//! `cargo bench --bench dashboard` renders the page of a full pool of `--trajectories N`
//! (default 1 000) trajectories of `--actions L` (default 1 000) actions, discrete (6
//! actions) and continuous (3 dimensions), `--runs R` times (default 20), and prints the
//! median and the slowest render and the page's size as a markdown table.

use std::time::Instant;

use tamrm::core::{ActionSeq, Pool, TaskConfig, TaskConfigInput, Trajectory};
use tamrm::registry::TaskStats;

#[path = "common/server.rs"]
mod server;
use server::arg_or;

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let n: usize = arg_or(&args, "--trajectories", 1_000);
    let len: usize = arg_or(&args, "--actions", 1_000);
    let runs: usize = arg_or(&args, "--runs", 20).max(1);
    println!("| pool | median render | slowest | page |");
    println!("|---|---|---|---|");
    for dim in [0usize, 3] {
        let trajectories: Vec<Trajectory> = (0..n)
            .map(|i| Trajectory {
                actions: if dim == 0 {
                    ActionSeq::Discrete((0..len).map(|j| ((i * 7 + j / 5) % 6) as u32).collect())
                } else {
                    ActionSeq::Continuous {
                        dim,
                        data: (0..len * dim)
                            .map(|j| ((i + j) as f32 * 0.01).sin())
                            .collect(),
                    }
                },
                score: (i as f64 * 0.37).sin() * 100.0,
                seq: i as u64 + 1,
            })
            .collect();
        let pool = Pool::restore(n, trajectories, 12_345, n as u64 + 1).expect("pool");
        let config = TaskConfig::resolve(&TaskConfigInput {
            num_actions: if dim == 0 { 6 } else { 0 },
            action_dim: dim as u32,
            pool_capacity: Some(n as u32),
            max_trajectory_len: Some(len as u32),
            ..Default::default()
        })
        .expect("config");
        let (worst, best) = pool.score_range().unwrap_or((0.0, 0.0));
        let stats = TaskStats {
            pool_size: pool.len(),
            pool_version: pool.version(),
            min_length: pool.l_min(),
            best_score: best,
            worst_score: worst,
            episodes_completed: 0,
            steps_shaped: 0,
            open_streams: 0,
        };
        let mut times = Vec::with_capacity(runs);
        let mut size = 0;
        for _ in 0..runs {
            let t = Instant::now();
            let page = tamrm::telemetry::task_page("bench", &config, &stats, &pool);
            times.push(t.elapsed().as_secs_f64() * 1e3);
            size = page.len();
            std::hint::black_box(page);
        }
        times.sort_by(f64::total_cmp);
        let kind = if dim == 0 {
            "discrete (6 actions)".to_string()
        } else {
            format!("continuous ({dim} dimensions)")
        };
        println!(
            "| {n} × {len}, {kind} | {:.1} ms | {:.1} ms | {:.2} MB |",
            times[runs / 2],
            times[runs - 1],
            size as f64 / 1e6
        );
    }
}
