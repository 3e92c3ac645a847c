//! One version: the workspace's `Cargo.toml` is the source, and every copy of it (the
//! crates, the Python package, `tamrm --version`, the start log, `tamrm_build_info`,
//! CHANGELOG.md, the Rust version the docs ask for) must agree with it.

use crate::common::Binary;
use std::path::Path;
use std::process::Command;
use tamrm::build_info;

fn repo_file(path: &str) -> String {
    let full = Path::new(env!("CARGO_MANIFEST_DIR")).join(path);
    std::fs::read_to_string(&full).unwrap_or_else(|e| panic!("{}: {e}", full.display()))
}

fn toml_file(path: &str) -> toml::Table {
    repo_file(path)
        .parse()
        .unwrap_or_else(|e| panic!("{path}: {e}"))
}

/// (version, rust-version) of `[workspace.package]`.
fn workspace() -> (String, String) {
    let root = toml_file("Cargo.toml");
    let package = root["workspace"]["package"].as_table().unwrap();
    (
        package["version"].as_str().unwrap().to_owned(),
        package["rust-version"].as_str().unwrap().to_owned(),
    )
}

#[test]
fn every_crate_and_the_python_package_take_the_workspace_version() {
    let (version, _) = workspace();
    assert_eq!(build_info::VERSION, version);
    for path in [
        "Cargo.toml",
        "clients/rust/Cargo.toml",
        "clients/python/native/Cargo.toml",
    ] {
        let package = toml_file(path)["package"].as_table().unwrap().clone();
        for key in ["version", "rust-version", "edition", "license"] {
            let inherited = package[key]
                .as_table()
                .and_then(|t| t.get("workspace"))
                .and_then(|w| w.as_bool());
            assert_eq!(inherited, Some(true), "{path}: {key}.workspace = true");
        }
    }
    // maturin takes the version of clients/python/native, i.e. the workspace's.
    let project = toml_file("clients/python/pyproject.toml")["project"]
        .as_table()
        .unwrap()
        .clone();
    assert!(
        !project.contains_key("version"),
        "pyproject.toml: no version of its own"
    );
    let dynamic = project["dynamic"].as_array().unwrap();
    assert!(dynamic.iter().any(|d| d.as_str() == Some("version")));
}

#[test]
fn the_changelog_starts_at_the_workspace_version() {
    let (version, _) = workspace();
    let changelog = repo_file("CHANGELOG.md");
    let newest = changelog
        .lines()
        .filter_map(|l| l.strip_prefix("## ["))
        .map(|l| l.split(']').next().unwrap())
        .find(|v| *v != "Unreleased")
        .expect("a released version in CHANGELOG.md");
    assert_eq!(newest, version);
}

#[test]
fn the_docs_ask_for_the_rust_the_workspace_needs() {
    let (_, rust) = workspace();
    for path in ["README.md", "CONTRIBUTING.md"] {
        let text = repo_file(path);
        let want = format!("Rust toolchain ({rust}+)");
        assert!(text.contains(&want), "{path} says {want:?}");
        // No other toolchain version anywhere in the file.
        for (i, _) in text.match_indices("Rust toolchain (") {
            assert!(text[i..].starts_with(&want), "{path}: {}", &text[i..i + 30]);
        }
    }
}

#[test]
fn the_proto_version_is_the_newest_baseline() {
    let mut versions: Vec<Vec<u32>> =
        std::fs::read_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join("proto/compat"))
            .unwrap()
            .filter_map(|e| {
                let name = e.unwrap().file_name().into_string().unwrap();
                let v = name
                    .strip_prefix("tamrm.v1.")?
                    .strip_suffix(".binpb")?
                    .to_owned();
                Some(v.split('.').map(|p| p.parse().unwrap()).collect())
            })
            .collect();
    versions.sort();
    let newest: Vec<String> = versions
        .last()
        .unwrap()
        .iter()
        .map(u32::to_string)
        .collect();
    assert_eq!(build_info::PROTO, newest.join("."));
}

#[test]
fn version_flag_and_start_log_report_the_build() {
    let (version, _) = workspace();
    let out = Command::new(env!("CARGO_BIN_EXE_tamrm"))
        .arg("--version")
        .output()
        .unwrap();
    assert!(out.status.success());
    let printed = String::from_utf8(out.stdout).unwrap();
    assert_eq!(printed.trim(), format!("tamrm {}", build_info::describe()));
    assert!(
        printed.starts_with(&format!("tamrm {version} (commit ")),
        "{printed}"
    );
    assert!(!build_info::COMMIT.is_empty());

    let server = Binary::start(&[]);
    let (status, log) = server.terminate();
    assert!(status.success(), "{log}");
    let line = format!("tamrm {}", build_info::describe());
    assert!(log.contains(&line), "no {line:?} in the start log:\n{log}");
}
