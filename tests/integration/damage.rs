//! The damage matrix of docs/storage.md, against the real binary: each file of a data dir
//! (the commit log, a snapshot, a task's metadata, the format marker, the lock file)
//! truncated, with a flipped byte, deleted, or replaced by the same file of another data
//! dir, after a graceful stop and after kill -9. Each case either starts and serves
//! exactly the acknowledged state, or refuses naming the damaged file; none starts with
//! less. And the way forward: `tamrm repair` says what a start would lose and, with
//! `--accept-loss`, cuts the log so that the data dir starts.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::*;
use crate::durability::{assert_bit_exact, copy_dir, snapshot};
use tamrm::proto;

/// How the server that filled a data dir stopped.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Stop {
    Graceful,
    Kill9,
}

/// `tamrm serve` on a data dir: serving (at an address), or exited with its stderr.
enum Outcome {
    Started(Child, std::net::SocketAddr),
    Refused(std::process::ExitStatus, String),
}

fn serve(data: &Path) -> Outcome {
    let tmp = tempfile::tempdir().unwrap();
    let (port_file, stderr) = (tmp.path().join("port"), tmp.path().join("stderr"));
    let mut child = Command::new(env!("CARGO_BIN_EXE_tamrm"))
        .args(["serve", "--listen", "127.0.0.1:0", "--port-file"])
        .arg(&port_file)
        .arg("--data-dir")
        .arg(data)
        .env_remove("TAMRM_DATA_DIR")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&stderr).unwrap())
        .spawn()
        .expect("spawn tamrm");
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return Outcome::Refused(status, std::fs::read_to_string(&stderr).unwrap());
        }
        if let Some(addr) = std::fs::read_to_string(&port_file)
            .ok()
            .and_then(|s| s.trim().parse().ok())
        {
            return Outcome::Started(child, addr);
        }
        assert!(Instant::now() < deadline, "tamrm neither served nor exited");
        std::thread::sleep(Duration::from_millis(10));
    }
}

/// Stops a started server as `stop` says.
fn stop(mut child: Child, how: Stop) {
    match how {
        Stop::Graceful => {
            let pid = child.id().to_string();
            Command::new("kill").args(["-TERM", &pid]).status().unwrap();
        }
        Stop::Kill9 => child.kill().unwrap(),
    }
    let status = child.wait().unwrap();
    if how == Stop::Graceful {
        assert!(status.success(), "{status:?}");
    }
}

/// Fills `data` through the real binary (two tasks, several groups in the log, pools
/// that replace trajectories), stops it as `how` says, and returns what it acknowledged.
async fn filled(data: &Path, how: Stop, salt: f64) -> Vec<proto::Pool> {
    let Outcome::Started(child, addr) = serve(data) else {
        panic!("a new data dir did not start")
    };
    let mut c = connect(addr).await;
    for id in ["a", "b"] {
        create(&mut c, id, discrete(4, 3, 3, 0, 1)).await;
    }
    for i in 0..24u32 {
        let id = if i % 3 == 0 { "b" } else { "a" };
        let acts: Vec<u32> = (0..=(i % 5)).map(|x| (x + i) % 4).collect();
        add(&mut c, id, dtraj(&acts, f64::from(i % 7) + salt)).await;
    }
    let (_, pools) = snapshot(&mut c).await;
    stop(child, how);
    pools
}

/// The files of the matrix, relative to the data dir.
fn files(data: &Path) -> Vec<(&'static str, PathBuf)> {
    let task = std::fs::read_dir(data.join("tasks"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.file_name().unwrap().to_str().unwrap().starts_with("a-"))
        .unwrap();
    let rel = |p: PathBuf| p.strip_prefix(data).unwrap().to_path_buf();
    vec![
        ("commit log", PathBuf::from("commits.log")),
        ("snapshot", rel(task.join("pool.json"))),
        ("task metadata", rel(task.join("task.json"))),
        ("format marker", PathBuf::from("tamrm.json")),
        ("lock file", PathBuf::from("LOCK")),
    ]
}

/// One kind of damage done to a file.
#[derive(Debug, Clone, Copy)]
enum Damage {
    /// Cut to this fraction of its length (in thousandths), at least one byte shorter.
    Truncated(u64),
    /// One bit of the byte at this fraction of its length (in thousandths) flipped.
    Flipped(u64),
    Deleted,
    /// Replaced by the same file of another data dir.
    Replaced,
}

const DAMAGES: &[Damage] = &[
    Damage::Truncated(0),
    Damage::Truncated(100),
    Damage::Truncated(500),
    Damage::Truncated(999),
    Damage::Flipped(0),
    Damage::Flipped(500),
    Damage::Flipped(999),
    Damage::Deleted,
    Damage::Replaced,
];

/// Does `damage` to `file`; false if it is not possible (an empty file cannot be cut or
/// have a byte flipped).
fn damage(file: &Path, other: &Path, d: Damage) -> bool {
    let b = std::fs::read(file).unwrap();
    let at = |k: u64| (b.len() as u64 * k / 1000) as usize;
    match d {
        _ if b.is_empty() && matches!(d, Damage::Truncated(_) | Damage::Flipped(_)) => {
            return false
        }
        Damage::Truncated(k) => std::fs::write(file, &b[..at(k).min(b.len() - 1)]).unwrap(),
        Damage::Flipped(k) => {
            let i = at(k).min(b.len() - 1);
            let mut b = b.clone();
            b[i] ^= 0x08;
            std::fs::write(file, b).unwrap()
        }
        Damage::Deleted => std::fs::remove_file(file).unwrap(),
        Damage::Replaced => {
            std::fs::copy(other, file).unwrap();
        }
    }
    true
}

/// Every file, every damage, after a graceful stop and after kill -9: a start serves
/// exactly the acknowledged pools, or exits non-zero naming the damaged file. Only the
/// lock file's damage starts (its content means nothing; the kernel's lock does).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_damage_starts_with_everything_or_is_refused_naming_the_file() {
    for how in [Stop::Graceful, Stop::Kill9] {
        let (base, other) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        let acknowledged = filled(base.path(), how, 0.0).await;
        filled(other.path(), how, 0.5).await;
        for (what, rel) in files(base.path()) {
            for &d in DAMAGES {
                let case = format!("{what} {d:?} after {how:?}");
                let copy = tempfile::tempdir().unwrap();
                copy_dir(base.path(), copy.path());
                let file = copy.path().join(&rel);
                if !damage(&file, &other.path().join(&rel), d) {
                    continue;
                }
                match serve(copy.path()) {
                    Outcome::Started(child, addr) => {
                        assert_eq!(what, "lock file", "{case}: started");
                        let mut c = connect(addr).await;
                        let (_, pools) = snapshot(&mut c).await;
                        assert_bit_exact(&pools, &acknowledged);
                        stop(child, Stop::Graceful);
                    }
                    Outcome::Refused(status, stderr) => {
                        assert!(!status.success(), "{case}: {status:?}");
                        let name = rel.file_name().unwrap().to_str().unwrap();
                        assert!(stderr.contains(name), "{case}: names no {name}:\n{stderr}");
                        assert!(!stderr.contains("panicked"), "{case}:\n{stderr}");
                    }
                }
            }
        }
    }
}

/// The operator's case: a clean stop, the log cut to half its length, a start. It
/// refuses, naming the log, the offset and the version each task can be restored at;
/// `tamrm repair` says so and changes nothing; `--accept-loss` cuts the log, and the data
/// dir then starts at exactly those versions.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_log_cut_after_a_clean_stop_is_refused_until_repair_accepts_the_loss() {
    let data = tempfile::tempdir().unwrap();
    let acknowledged = filled(data.path(), Stop::Graceful, 0.0).await;
    let log = data.path().join("commits.log");
    let len = std::fs::metadata(&log).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&log)
        .unwrap()
        .set_len(len / 2)
        .unwrap();
    let Outcome::Refused(status, stderr) = serve(data.path()) else {
        panic!("a cut log started")
    };
    assert!(!status.success());
    assert!(stderr.contains(log.to_str().unwrap()), "{stderr}");
    assert!(stderr.contains("after a clean stop"), "{stderr}");
    assert!(
        stderr.contains(&format!("ends at offset {len}")),
        "{stderr}"
    );
    let restorable = |s: &str, id: &str| -> u64 {
        let key = format!("\"{id}\" at version ");
        let at = s.find(&key).unwrap_or_else(|| panic!("no {key} in {s}")) + key.len();
        s[at..]
            .split(|c: char| !c.is_ascii_digit())
            .next()
            .unwrap()
            .parse()
            .unwrap()
    };
    let (ra, rb) = (restorable(&stderr, "a"), restorable(&stderr, "b"));
    let version = |id: &str| {
        acknowledged
            .iter()
            .find(|p| p.task_id == id)
            .unwrap()
            .pool_version
    };
    assert!(ra < version("a") || rb < version("b"), "{stderr}");

    let repair = |args: &[&str]| {
        let out = Command::new(env!("CARGO_BIN_EXE_tamrm"))
            .arg("repair")
            .arg("--data-dir")
            .arg(data.path())
            .args(args)
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout).into_owned()
            + &String::from_utf8_lossy(&out.stderr);
        (out.status.success(), text)
    };
    let (ok, shown) = repair(&[]);
    assert!(!ok, "{shown}");
    assert!(
        shown.contains(&format!("task \"a\": restorable at version {ra}")),
        "{shown}"
    );
    assert!(shown.contains("--accept-loss"), "{shown}");
    assert_eq!(
        std::fs::metadata(&log).unwrap().len(),
        len / 2,
        "nothing changed"
    );
    assert!(matches!(serve(data.path()), Outcome::Refused(..)));

    let (ok, done) = repair(&["--accept-loss"]);
    assert!(ok, "{done}");
    let Outcome::Started(child, addr) = serve(data.path()) else {
        panic!("a repaired data dir does not start")
    };
    let mut c = connect(addr).await;
    assert_eq!(get_pool(&mut c, "a").await.pool_version, ra);
    assert_eq!(get_pool(&mut c, "b").await.pool_version, rb);
    stop(child, Stop::Graceful);
    let (ok, again) = repair(&[]);
    assert!(ok && again.contains("nothing to repair"), "{again}");
}

/// Bytes after the log's end: after a clean stop they cannot be a crash's torn write, and
/// the start refuses; after kill -9 they are one (never acknowledged), and the start cuts
/// them, serving everything acknowledged.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bytes_past_the_end_are_refused_after_a_clean_stop_and_cut_after_a_crash() {
    for how in [Stop::Graceful, Stop::Kill9] {
        let data = tempfile::tempdir().unwrap();
        let acknowledged = filled(data.path(), how, 0.0).await;
        let log = data.path().join("commits.log");
        let mut b = std::fs::read(&log).unwrap();
        let len = b.len();
        b.extend_from_slice(b"TGRP\x40\x00\x00\x00\x01\x00");
        std::fs::write(&log, &b).unwrap();
        match (serve(data.path()), how) {
            (Outcome::Refused(_, stderr), Stop::Graceful) => {
                assert!(stderr.contains(&format!("from offset {len}")), "{stderr}")
            }
            (Outcome::Started(child, addr), Stop::Kill9) => {
                let mut c = connect(addr).await;
                assert_bit_exact(&snapshot(&mut c).await.1, &acknowledged);
                stop(child, Stop::Graceful);
            }
            (Outcome::Started(..), _) => panic!("{how:?}: started"),
            (Outcome::Refused(_, e), _) => panic!("{how:?}: refused: {e}"),
        }
    }
}
