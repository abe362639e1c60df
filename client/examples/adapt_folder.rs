//! Online adaptation from a program: upload a folder of unlabelled target images of a category
//! (one ack per image, resent as needed when the connection breaks or the buffer is full),
//! start an adaptation job (idempotent thanks to its client job id) and follow its events until
//! the gate activates the adapted model or not.
//!
//! ```sh
//! cargo run --release -p udapose-client --example adapt_folder -- 127.0.0.1:50051 car path/to/images
//! ```

use anyhow::{Context, Result, bail};
use tokio_stream::iter;
use udapose_client::{AdaptOverrides, Client, JobState, new_client_job_id, state_name, target_ack};

#[tokio::main]
async fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [endpoint, category, folder] = args.as_slice() else {
        bail!("usage: adapt_folder ENDPOINT CATEGORY IMAGES_DIR");
    };
    let mut files: Vec<_> = std::fs::read_dir(folder)
        .with_context(|| format!("listing {folder}"))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "png" || e == "jpg" || e == "webp"))
        .collect();
    files.sort();
    let images =
        files.iter().map(|p| Ok((p.display().to_string(), std::fs::read(p)?))).collect::<std::io::Result<Vec<_>>>()?;
    let client = Client::connect(endpoint).await?;

    let mut uploads = client.stream_targets(category, iter(images));
    let mut accepted = 0;
    while let Some(upload) = uploads.message().await? {
        match upload.ack.status() {
            target_ack::Status::Accepted => accepted += 1,
            target_ack::Status::Duplicate => {}
            _ => println!("{}: {}", upload.name, upload.ack.reason),
        }
    }
    println!("{accepted} new images buffered");

    let job = client.start_job(category, AdaptOverrides::default(), Some(&new_client_job_id())).await?;
    let mut events = client.watch_job(&job.job_id, 0).await?;
    let mut last = job.state;
    while let Some(e) = events.message().await? {
        println!(
            "{} round {}/{} fired {:.3}: {}",
            state_name(e.state),
            e.round,
            e.max_rounds,
            e.fired_ratio,
            e.message
        );
        last = e.state;
    }
    let job = client.get_job(&job.job_id).await?;
    if last == JobState::Activated as i32 {
        println!("version {} is active", job.version);
        Ok(())
    } else {
        bail!("job {} ended {}: {}", job.job_id, state_name(last), job.reason)
    }
}
