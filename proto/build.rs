//! Compiles `trove.proto` with protox (a pure-Rust protobuf compiler), so building needs
//! only cargo: no system `protoc`. The compiled descriptors are also written out, encoded,
//! for server reflection (`FILE_DESCRIPTOR_SET` in the crate).

use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=trove.proto");
    let descriptors = protox::compile(["trove.proto"], ["."])?;
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("trove_descriptor.bin"), descriptors.encode_to_vec())?;
    // A batch's tasks as `Bytes`: the coordinator keeps them, without a copy, until the
    // batch is answered, to send them again if a busy worker refuses them.
    tonic_prost_build::configure()
        .bytes(".trove.v1.CastBatch.tasks")
        .build_client(true)
        .build_server(true)
        .compile_fds(descriptors)?;
    Ok(())
}
