//! Compiles `insitu.proto` with protox (pure Rust), so no system `protoc` is needed.

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=insitu.proto");
    let fds = protox::compile(["insitu.proto"], ["."])?;
    tonic_prost_build::configure()
        .bytes(".insitu.v1")
        .compile_fds(fds)?;
    Ok(())
}
