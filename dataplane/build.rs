//! Generates the prost types from the same `proto/` the Python services use, with
//! protox (a protobuf compiler in Rust: no protoc to install), and embeds the
//! descriptor set so a service can refuse fields a schema does not have, as the
//! Python runner does (`swarmrec.wire.codec.check_fields`).
use std::path::PathBuf;

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..").join("proto");
    let dir = root.join("swarmrec").join("v1");
    let mut files: Vec<PathBuf> = std::fs::read_dir(&dir)
        .expect("proto/swarmrec/v1")
        .map(|e| e.expect("proto entry").path())
        .filter(|p| p.extension().is_some_and(|x| x == "proto"))
        .collect();
    files.sort();
    let fds = protox::compile(&files, [&root]).expect("proto/ compiles");
    let out = PathBuf::from(std::env::var("OUT_DIR").expect("OUT_DIR"));
    std::fs::write(out.join("descriptors.bin"), prost::Message::encode_to_vec(&fds)).expect("write descriptors");
    prost_build::Config::new().compile_fds(fds).expect("prost codegen");
    println!("cargo:rerun-if-changed={}", dir.display());
}
