//! Compiles `proto/cellgate/v1/*.proto` into Rust with prost. The .proto files are parsed
//! by protox (pure Rust), so no system `protoc` is needed.

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=proto");
    let dir = PathBuf::from("proto/cellgate/v1");
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
    let fds = protox::compile(&files, ["proto"])?;
    prost_build::Config::new().compile_fds(fds)?;
    Ok(())
}
