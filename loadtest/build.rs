//! Compiles the server's gRPC API (`../proto/crossview/v1/*.proto`) into client stubs with a
//! vendored `protoc`, so the load generator does not depend on how the library exposes them.
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dir = PathBuf::from("../proto");
    let mut protos: Vec<PathBuf> = std::fs::read_dir(dir.join("crossview/v1"))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "proto"))
        .collect();
    protos.sort();
    if std::env::var_os("PROTOC").is_none() {
        // SAFETY: build scripts are single-threaded at this point.
        unsafe { std::env::set_var("PROTOC", protoc_bin_vendored::protoc_bin_path()?) };
    }
    tonic_prost_build::configure()
        .build_server(false)
        .compile_protos(&protos, &[dir])?;
    println!("cargo:rerun-if-changed=../proto");
    Ok(())
}
