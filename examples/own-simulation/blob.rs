use insitu_client::{SimClient, Step};
use std::time::Duration;

#[tokio::main]
async fn main() -> Result<(), Box<dyn std::error::Error>> {
    let addr = std::env::args().nth(1).ok_or("usage: blob HOST:PORT")?;
    let mut client = SimClient::connect(&addr, None).await?; // the generator-node's address
    const N: usize = 64;
    for step in 0..10u64 {
        let cx = 16.0 + 2.0 * step as f32; // a blob moving along x
        let blob = |x: f32, y: f32, z: f32| {
            (-((x - cx).powi(2) + (y - 32.0).powi(2) + (z - 32.0).powi(2)) / 128.0).exp()
        };
        let field: Vec<f32> = (0..N * N * N) // x varies fastest
            .map(|i| blob((i % N) as f32, (i / N % N) as f32, (i / (N * N)) as f32))
            .collect();
        let time = 0.1 * step as f64;
        let dims = [N as u32; 3];
        client
            .push_step(Step::whole_f32_owned(step, time, dims, field))
            .await?;
    }
    client.close(Duration::from_secs(600)).await?; // flush: every step is stored
    println!("pushed 10 steps of {N}^3");
    Ok(())
}
