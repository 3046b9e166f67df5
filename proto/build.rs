//! Compile `dray/v1/*.proto` without a system `protoc`: protox (a protobuf compiler in
//! pure Rust) parses them into a `FileDescriptorSet`, tonic-prost-build generates the
//! messages, clients and servers from it, and the encoded set is written to `OUT_DIR` for
//! gRPC server reflection.

use std::path::PathBuf;

use prost::Message;

const PROTOS: &[&str] = &[
    "dray/v1/render.proto",
    "dray/v1/cluster.proto",
    "dray/v1/rays.proto",
    "dray/v1/cache.proto",
    "dray/v1/package.proto",
];

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let root = PathBuf::from(std::env::var("CARGO_MANIFEST_DIR")?);
    let out_dir = PathBuf::from(std::env::var("OUT_DIR")?);
    println!("cargo:rerun-if-changed=dray");
    for p in PROTOS {
        println!("cargo:rerun-if-changed={p}");
    }

    // Source info is kept (include_source_info) so reflection clients such as
    // `grpcurl describe` show the .proto comments; imports (the well-known types) are
    // included so the set is self-contained.
    let fds = protox::compile(PROTOS, [&root])?;
    std::fs::write(out_dir.join("dray_descriptor.bin"), fds.encode_to_vec())?;

    tonic_prost_build::configure()
        .build_client(true)
        .build_server(true)
        .build_transport(true)
        .emit_rerun_if_changed(false)
        // An encoded image is shared by every caller that asked for it (coordinator
        // `image_memo`): `Bytes` is a reference-counted buffer, not a copy per stream.
        .bytes(".dray.v1.GetImageResponse.data")
        .compile_fds(fds)?;
    Ok(())
}
