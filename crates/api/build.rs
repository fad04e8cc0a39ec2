//! Compiles `proto/crossview/v1/*.proto` into tonic/prost code with a vendored `protoc`,
//! so a fresh machine needs no system protobuf compiler.
use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // The protos live at the repository root (the Python client and the docs use them too).
    let dir = PathBuf::from("../../proto");
    let mut protos: Vec<PathBuf> = std::fs::read_dir(dir.join("crossview/v1"))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "proto"))
        .collect();
    protos.sort();
    if std::env::var_os("PROTOC").is_none() {
        // SAFETY: build scripts are single-threaded at this point.
        #[allow(unsafe_code)]
        unsafe {
            std::env::set_var("PROTOC", protoc_bin_vendored::protoc_bin_path()?)
        };
    }
    let out = PathBuf::from(std::env::var("OUT_DIR")?);
    tonic_prost_build::configure()
        .file_descriptor_set_path(out.join("crossview_descriptor.bin"))
        .compile_protos(&protos, &[dir, protoc_bin_vendored::include_path()?])?;
    println!("cargo:rerun-if-changed=../../proto");
    Ok(())
}
