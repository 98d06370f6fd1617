//! Generates the prost types from the same `proto/` the Python services use, with
//! protox (a protobuf compiler in Rust: no protoc to install), and embeds the
//! descriptor set so a service can refuse fields a schema does not have, as the
//! Python runner does (`swarmrec.wire.codec.check_fields`).
//!
//! On x86-64 it also compiles numpy's argsort (the vendored x86-simd-sort,
//! `dataplane/vendor/README.md`) once per level numpy dispatches to, with numpy's
//! flags for that level, so the compiled services break ties as numpy does.
use std::path::PathBuf;

/// numpy 2.4.6's compiler flags for its x86-64 levels (meson_cpu/x86/meson.build):
/// X86_V2 is its baseline, X86_V3 and X86_V4 each add to the one below.
const X86_V2: &[&str] = &[
    "-msse", "-msse2", "-msse3", "-mssse3", "-msse4.1", "-msse4.2", "-mpopcnt",
];
const X86_V3: &[&str] = &[
    "-mavx", "-mavx2", "-mfma", "-mbmi", "-mbmi2", "-mlzcnt", "-mf16c", "-mmovbe",
];
const X86_V4: &[&str] = &["-mavx512f", "-mavx512cd", "-mavx512vl", "-mavx512bw", "-mavx512dq"];

fn compile_argsort() {
    let crate_dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let vendor = crate_dir.join("vendor").join("x86-simd-sort").join("src");
    let levels: [(&str, Vec<&str>); 2] = [
        ("x86_v3", [X86_V2, X86_V3].concat()),
        ("x86_v4", [X86_V2, X86_V3, X86_V4].concat()),
    ];
    for (level, flags) in levels {
        let mut build = cc::Build::new();
        build
            .cpp(true)
            .std("c++17")
            .include(&vendor)
            .file(crate_dir.join("csrc").join("argsort.cpp"));
        build.define("SWARMREC_LEVEL", level).warnings(false);
        for flag in flags {
            build.flag(flag);
        }
        build.compile(&format!("swarmrec_argsort_{level}"));
    }
    println!("cargo:rerun-if-changed={}", crate_dir.join("csrc").display());
    println!("cargo:rerun-if-changed={}", crate_dir.join("vendor").display());
}

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
    if std::env::var("CARGO_CFG_TARGET_ARCH").as_deref() == Ok("x86_64") {
        compile_argsort();
    }
}
