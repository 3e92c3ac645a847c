//! Compiles `proto/` without a system `protoc`: `protox` parses the files into a
//! descriptor set, which `tonic-prost-build` turns into Rust code. The encoded descriptor
//! set is also written to `OUT_DIR` for the server-reflection service.
use prost::Message;
use std::{env, fs, path::PathBuf};

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
    Ok(())
}
