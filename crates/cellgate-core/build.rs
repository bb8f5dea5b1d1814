//! Compiles the bus contract, `proto/cellgate/v1/*.proto` at the top of the workspace, into
//! Rust with prost, and its JSON mapping with pbjson. The .proto files are parsed by protox (pure Rust), so no system `protoc`
//! is needed.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = PathBuf::from("../../proto");
    println!("cargo:rerun-if-changed={}", root.display());
    let dir = root.join("cellgate/v1");
    let mut files = Vec::new();
    for entry in std::fs::read_dir(&dir)? {
        let path = entry?.path();
        if path.extension().is_some_and(|e| e == "proto") {
            println!("cargo:rerun-if-changed={}", path.display());
            files.push(path);
        }
    }
    // Sorted so the generated code does not depend on directory order.
    files.sort();
    let fds = protox::compile(&files, [&root])?;
    let descriptors = prost::Message::encode_to_vec(&fds);
    prost_build::Config::new().compile_fds(fds)?;
    // The proto3 JSON mapping of every message (serde), for `--json` and the console: field
    // names as in the .proto files, enums by name, fields at their defaults included.
    pbjson_build::Builder::new()
        .register_descriptors(&descriptors)?
        .preserve_proto_field_names()
        .emit_fields()
        .build(&[".cellgate.v1"])?;
    Ok(())
}
