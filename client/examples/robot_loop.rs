//! A robot's perception loop: frames from a camera (here: the images of a folder, replayed at a
//! fixed rate) stream to the server over one bidirectional `EstimateStream`; poses come back in
//! order, matched by `frame_id`, while the next frames are already on their way.
//!
//! ```sh
//! cargo run --release -p udapose-client --example robot_loop -- 127.0.0.1:50051 car path/to/frames 10
//! ```
//! Arguments: endpoint (or several, comma-separated: the stream moves to another when its server
//! goes away), category, folder of PNG/JPEG/WebP frames, frames per second.

use std::time::{Duration, Instant};

use anyhow::{Context, Result, bail};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use udapose_client::Client;
use udapose_proto::v1::{EstimateRequest, estimate_request::Input};

#[tokio::main]
async fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [endpoint, category, folder, fps] = args.as_slice() else {
        bail!("usage: robot_loop ENDPOINT CATEGORY FRAMES_DIR FPS");
    };
    let fps: f64 = fps.parse().context("FPS")?;
    let mut frames: Vec<_> = std::fs::read_dir(folder)
        .with_context(|| format!("listing {folder}"))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "png" || e == "jpg" || e == "webp"))
        .collect();
    frames.sort();
    let client = Client::connect(endpoint).await?;

    // The camera: one frame per tick. A bounded channel: if the server falls behind, the
    // camera waits instead of piling frames up (a real robot would drop stale frames).
    let (tx, rx) = mpsc::channel::<EstimateRequest>(4);
    let category = category.clone();
    let camera = tokio::spawn(async move {
        let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / fps));
        for (i, path) in frames.iter().enumerate() {
            tick.tick().await;
            let Ok(bytes) = std::fs::read(path) else { continue };
            let frame = EstimateRequest {
                category: category.clone(),
                input: Some(Input::Image(bytes)),
                frame_id: format!("{i}:{}", path.display()),
                ..Default::default()
            };
            if tx.send(frame).await.is_err() {
                break;
            }
        }
    });

    let started = Instant::now();
    let mut poses = client.estimate_stream(ReceiverStream::new(rx)).await?;
    let mut n = 0;
    while let Some(response) = poses.message().await? {
        n += 1;
        match (&response.error, response.estimates.first()) {
            (Some(e), _) => println!("{}: error {}: {}", response.frame_id, e.code, e.message),
            (None, Some(p)) => println!(
                "{}: azimuth {:7.1}°  elevation {:5.1}°  theta {:6.1}°  score {:.3}  ({:.0} ms, {})",
                response.frame_id,
                p.azimuth_deg,
                p.elevation_deg,
                p.theta_deg,
                p.score,
                response.timings.as_ref().map_or(0.0, |t| t.total_ms),
                response.model_version
            ),
            (None, None) => println!("{}: no estimate", response.frame_id),
        }
    }
    camera.await?;
    println!("{n} frames in {:.1} s", started.elapsed().as_secs_f64());
    Ok(())
}
