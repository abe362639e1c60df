//! Compiles `udapose/v1/*.proto` with protox (pure Rust, so no system `protoc`),
//! generates prost messages + tonic client/server from the resulting descriptor
//! set, and writes that set to OUT_DIR for gRPC reflection.

use std::{env, fs, path::PathBuf};

use protox::prost::Message;

const PROTOS: &[&str] = &["udapose/v1/adapt.proto", "udapose/v1/models.proto", "udapose/v1/pose.proto"];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    for proto in PROTOS {
        println!("cargo:rerun-if-changed={proto}");
    }
    let fds = protox::compile(PROTOS, ["."])?;
    let out_dir = PathBuf::from(env::var("OUT_DIR")?);
    fs::write(out_dir.join("udapose_descriptor.bin"), fds.encode_to_vec())?;
    tonic_prost_build::configure().compile_fds(fds)?;
    Ok(())
}
