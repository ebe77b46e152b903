//! Compiles `trove.proto` with protox (a pure-Rust protobuf compiler), so building needs
//! only cargo: no system `protoc`.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=trove.proto");
    let descriptors = protox::compile(["trove.proto"], ["."])?;
    tonic_prost_build::configure().build_client(true).build_server(true).compile_fds(descriptors)?;
    Ok(())
}
