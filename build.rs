//! Compiles `proto/` without a system `protoc`: `protox` parses the files into a
//! descriptor set, which `tonic-prost-build` turns into Rust code. The encoded descriptor
//! set is also written to `OUT_DIR` for the server-reflection service.
//!
//! Also sets the build facts of [`tamrm::build_info`]: the proto's API version (the newest
//! baseline in `proto/compat/`, which every change of the proto lands with) and the commit
//! (`TAMRM_COMMIT` if set, as a build from an sdist has no git, else `git rev-parse`).
use prost::Message;
use std::{env, fs, path::Path, path::PathBuf, process::Command};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let protos = ["proto/tamrm/v1/shaping.proto"];
    println!("cargo:rerun-if-changed=proto");
    let fds = protox::compile(protos, ["proto"])?;
    let out = PathBuf::from(env::var("OUT_DIR")?);
    fs::write(out.join("tamrm_descriptor.bin"), fds.encode_to_vec())?;
    tonic_prost_build::configure()
        .build_server(true)
        .build_client(true)
        .compile_fds(fds)?;
    println!("cargo:rustc-env=TAMRM_PROTO_VERSION={}", proto_version()?);
    println!("cargo:rustc-env=TAMRM_COMMIT={}", commit());
    Ok(())
}

/// `1.3` from `proto/compat/tamrm.v1.1.3.binpb`, the newest baseline by version.
fn proto_version() -> Result<String, Box<dyn std::error::Error>> {
    let mut versions: Vec<Vec<u32>> = Vec::new();
    for entry in fs::read_dir("proto/compat")? {
        let name = entry?.file_name().to_string_lossy().into_owned();
        if let Some(v) = name
            .strip_prefix("tamrm.v1.")
            .and_then(|n| n.strip_suffix(".binpb"))
        {
            versions.push(v.split('.').map(str::parse).collect::<Result<_, _>>()?);
        }
    }
    let newest = versions
        .into_iter()
        .max()
        .ok_or("no baseline in proto/compat")?;
    Ok(newest
        .iter()
        .map(u32::to_string)
        .collect::<Vec<_>>()
        .join("."))
}

fn commit() -> String {
    println!("cargo:rerun-if-env-changed=TAMRM_COMMIT");
    if let Ok(c) = env::var("TAMRM_COMMIT") {
        return c;
    }
    let git = |args: &[&str]| -> Option<String> {
        let out = Command::new("git").args(args).output().ok()?;
        let text = String::from_utf8(out.stdout).ok()?;
        (out.status.success() && !text.trim().is_empty()).then(|| text.trim().to_owned())
    };
    // Rebuild when HEAD moves (a commit, a checkout), not on every build.
    let branch = git(&["symbolic-ref", "-q", "HEAD"]);
    for file in ["HEAD", "packed-refs"].into_iter().chain(branch.as_deref()) {
        if let Some(path) = git(&["rev-parse", "--git-path", file]) {
            if Path::new(&path).exists() {
                println!("cargo:rerun-if-changed={path}");
            }
        }
    }
    git(&["rev-parse", "--short=12", "HEAD"]).unwrap_or_else(|| "unknown".to_owned())
}
