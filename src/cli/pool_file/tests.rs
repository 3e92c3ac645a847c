use super::*;
use crate::service::convert::config_proto;

fn fixtures() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("clients/python/tests/fixtures/pool")
}

fn cases() -> serde_json::Value {
    let text = std::fs::read_to_string(fixtures().join("cases.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn config_json(c: &TaskConfig) -> serde_json::Value {
    let mut text = String::new();
    write_config(c, &mut text);
    serde_json::from_str(&text).unwrap()
}

fn hex_bits(s: &serde_json::Value) -> u64 {
    u64::from_str_radix(s.as_str().unwrap().trim_start_matches("0x"), 16).unwrap()
}

#[test]
fn every_refused_fixture_is_refused_at_the_line_cases_json_names() {
    let cases = cases();
    let refused = cases["refused"].as_object().unwrap();
    assert!(
        refused.len() >= 17,
        "cases.json lists {} refused files",
        refused.len()
    );
    for (name, case) in refused {
        let path = fixtures().join(name);
        let err = match read(&path) {
            Err(ReadError::Refused(e)) => e,
            Err(e) => panic!("{name}: {e}"),
            Ok(_) => panic!("{name} was read, but cases.json says it is refused"),
        };
        let line = case["line"].as_u64().unwrap() as usize;
        assert_eq!(err.line, line, "{name} ({}): {err}", case["why"]);
        assert!(
            err.to_string().contains(&format!("{name}, line {line}: ")),
            "{err}"
        );
    }
    // Every bad-*.jsonl is in cases.json.
    for entry in std::fs::read_dir(fixtures()).unwrap() {
        let name = entry.unwrap().file_name().to_string_lossy().into_owned();
        if name.starts_with("bad-") {
            assert!(refused.contains_key(&name), "{name} is not in cases.json");
        }
    }
}

#[test]
fn every_valid_fixture_reads_bit_for_bit_as_cases_json_says_and_writes_back_the_same() {
    let cases = cases();
    let valid = cases["valid"].as_object().unwrap();
    assert_eq!(valid.len(), 2);
    for (name, want) in valid {
        let file = read(&fixtures().join(name)).unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(file.task_id, want["task_id"].as_str().unwrap(), "{name}");
        assert_eq!(config_json(&file.config), want["config"], "{name}");
        assert_eq!(file.pool_version, want["pool_version"].as_u64().unwrap());
        let trajectories = want["trajectories"].as_array().unwrap();
        assert_eq!(file.trajectories.len(), trajectories.len(), "{name}");
        for (got, want) in file.trajectories.iter().zip(trajectories) {
            assert_eq!(got.seq, want["seq"].as_u64().unwrap(), "{name}");
            assert_eq!(got.score.to_bits(), hex_bits(&want["score_bits"]), "{name}");
            if let Some(actions) = want.get("actions") {
                let actions: Vec<u32> = serde_json::from_value(actions.clone()).unwrap();
                assert_eq!(got.actions, actions, "{name}");
                assert!(got.action_vectors.is_empty());
            } else {
                let rows: Vec<Vec<u32>> =
                    serde_json::from_value(want["action_bits"].clone()).unwrap();
                let bits: Vec<u32> = got.action_vectors.iter().map(|v| v.to_bits()).collect();
                assert_eq!(bits, rows.concat(), "{name}");
                assert!(got.actions.is_empty());
            }
        }
        // Written and read again: the same values, bit for bit.
        let pool = proto::Pool {
            task_id: file.task_id.clone(),
            pool_version: file.pool_version,
            trajectories: file.trajectories.clone(),
            next_seq: 0,
        };
        let mut out = Vec::new();
        write_lines(&mut out, &file.task_id, &file.config, &pool).unwrap();
        assert!(out.ends_with(b"\n"));
        let again = read_bytes("again", &out).unwrap();
        assert_eq!(again, file, "{name}");
        assert!(again.config.same_as(&file.config));
        assert_eq!(config_proto(&again.config), config_proto(&file.config));
    }
}

fn refused(text: &str) -> PoolFileError {
    read_bytes("f", text.as_bytes()).expect_err("refused")
}

const HEADER: &str = r#"{"format": "tamrm-pool", "version": 1, "task_id": "t", "config": {"num_actions": 2, "action_dim": 0, "pool_capacity": 2, "k": 1, "start_step": 0, "min_pool_size": 1, "alpha": 1, "beta": 0, "gamma": 1, "max_trajectory_len": 3, "gate_potential": false, "require_score_spread": false}, "pool_version": 1, "trajectories": 1}"#;

#[test]
fn what_a_reader_refuses_is_named_with_its_line_and_problem() {
    let e = refused("");
    assert_eq!(e.line, 1);
    assert!(e.problem.contains("empty"), "{e}");
    let e = refused(&format!(
        "{HEADER}\n{{\"seq\": 1, \"seq\": 2, \"score\": 1, \"actions\": [0]}}\n"
    ));
    assert_eq!(e.line, 2);
    assert!(e.problem.contains("\"seq\" appears twice"), "{e}");
    let e = refused(&format!(
        "{HEADER}\n{{\"seq\": 1, \"score\": 1, \"actions\": [0.0]}}\n"
    ));
    assert!(e.problem.contains("actions[0]: must be an integer"), "{e}");
    let e = refused(&format!("{HEADER}\n\n"));
    assert_eq!((e.line, e.problem.contains("empty line")), (2, true), "{e}");
    let e = read_bytes("f", &[HEADER.as_bytes(), b"\n\xff\n"].concat()).unwrap_err();
    assert_eq!(e.line, 2);
    assert!(e.problem.contains("not UTF-8"), "{e}");
    let e = refused(&HEADER.replace("\"t\"", "\"a b\""));
    assert!(e.problem.contains("task_id"), "{e}");
    let e = refused(&HEADER.replace("\"k\": 1", "\"k\": 1, \"kk\": 1"));
    assert!(e.problem.contains("config.kk: an unknown"), "{e}");
    let e = refused(&HEADER.replace("\"pool_version\": 1", "\"pool_version\": -1"));
    assert!(e.problem.contains("pool_version"), "{e}");
    let e = refused("[1]\n");
    assert!(e.problem.contains("a JSON array"), "{e}");
    // A \r\n line end and a last line without \n are read.
    let ok = format!("{HEADER}\r\n{{\"seq\": 5, \"score\": -0.0, \"actions\": [1, 0]}}");
    let file = read_bytes("f", ok.as_bytes()).unwrap();
    assert_eq!(file.trajectories[0].actions, [1, 0]);
    assert_eq!(file.trajectories[0].score.to_bits(), (-0.0f64).to_bits());
}

#[test]
fn a_path_is_written_through_a_renamed_temporary_file() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("pool.jsonl");
    std::fs::write(&path, "old").unwrap();
    let file = read(&fixtures().join("continuous.jsonl")).unwrap();
    let pool = proto::Pool {
        trajectories: file.trajectories.clone(),
        pool_version: file.pool_version,
        ..Default::default()
    };
    assert_eq!(write_path(&path, "x", &file.config, &pool).unwrap(), 3);
    let names: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert_eq!(names.len(), 1, "a temporary file was left behind");
    assert_eq!(read(&path).unwrap().trajectories, file.trajectories);
    // A directory that does not exist: an error, and no file.
    let err = write_path(&dir.path().join("no/such.jsonl"), "x", &file.config, &pool);
    assert!(err.is_err());
}
