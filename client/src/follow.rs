//! `udapose adapt` and `udapose jobs watch`: upload target images, start a job, follow its
//! events to the end (across a server restart).

use std::{
    path::PathBuf,
    process::ExitCode,
    time::{Duration, Instant},
};

use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use serde_json::json;
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;
use udapose_client::{AdaptOverrides, Client, Error as ClientError, GateCriterion, JobEvent, JobState, is_terminal};

use crate::{AdaptArgs, JOB_NOT_ACTIVATED, output, output::UploadSummary};

/// `udapose adapt`: upload, start a job, follow it.
pub(crate) async fn adapt(client: &Client, args: AdaptArgs) -> Result<ExitCode> {
    let files = output::list_images(&args.images)?;
    let summary = upload(client, &args.category, &files, args.anchor, args.json).await?;
    if args.json {
        println!("{}", summary.json());
    } else {
        summary.lines().iter().for_each(|l| println!("{l}"));
    }
    if args.anchor {
        return Ok(ExitCode::SUCCESS); // anchors start no job
    }

    let overrides = AdaptOverrides { max_rounds: args.max_rounds, learning_rate: args.learning_rate, seed: args.seed };
    let client_job_id = args.client_job_id.unwrap_or_else(udapose_client::new_client_job_id);
    let job = client
        .start_job(&args.category, overrides, Some(&client_job_id))
        .await
        .with_context(|| format!("starting a job for {}", args.category))?;
    if args.json {
        println!("{}", json!({ "job": output::job_json(&job)? }));
    } else {
        println!("{}", output::job_started_line(&job));
    }
    if args.no_follow {
        return Ok(ExitCode::SUCCESS);
    }
    watch(client, &job.job_id, 0, args.json).await
}

/// Uploads `files` over StreamTargets (to the buffer, or the anchor set) with a progress bar (on
/// stderr, when it is a terminal).
async fn upload(client: &Client, category: &str, files: &[PathBuf], anchor: bool, json: bool) -> Result<UploadSummary> {
    let bar = ProgressBar::new(files.len() as u64).with_style(
        ProgressStyle::with_template("{spinner} uploading [{bar:30}] {pos}/{len} {msg} ({eta})")
            .expect("a valid template")
            .progress_chars("=> "),
    );
    if json {
        bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
    }
    // Files are read as the stream takes them (a few at a time), not all at once.
    let (tx, rx) = mpsc::channel(4);
    let reader = tokio::spawn({
        let files = files.to_vec();
        async move {
            for file in files {
                let name = file.file_name().map_or_else(|| file.display().to_string(), |n| n.to_string_lossy().into());
                let bytes = tokio::fs::read(&file).await.with_context(|| format!("reading {}", file.display()))?;
                if tx.send((name, bytes)).await.is_err() {
                    break;
                }
            }
            anyhow::Ok(())
        }
    });
    let mut summary = UploadSummary { anchor, ..UploadSummary::new(category) };
    let images = ReceiverStream::new(rx);
    let mut uploads =
        if anchor { client.stream_anchors(category, images) } else { client.stream_targets(category, images) };
    let result = async {
        while let Some(upload) = uploads.message().await? {
            summary.add(&upload);
            bar.set_message(summary.counts());
            bar.inc(1);
        }
        anyhow::Ok(())
    }
    .await;
    bar.finish_and_clear();
    result.with_context(|| {
        format!("uploading to {category} ({} of {} images acknowledged)", summary.images, files.len())
    })?;
    reader.await.context("the file reader")??;
    Ok(summary)
}

/// How long `watch` keeps reconnecting to a server it lost (a restart takes seconds; the job
/// survives it and resumes there).
const RECONNECT: Duration = Duration::from_secs(120);

/// Follows a job's events to its end; the exit status says whether it was ACTIVATED.
pub(crate) async fn watch(client: &Client, job_id: &str, after_seq: u64, json: bool) -> Result<ExitCode> {
    let mut followed = Followed { seq: after_seq, last: None, gate: Vec::new() };
    let mut lost: Option<Instant> = None;
    loop {
        let seen = followed.seq;
        match followed.until_end(client, job_id, json).await {
            Ok(()) => break,
            Err(e @ (ClientError::GaveUp { .. } | ClientError::Connect { .. })) => {
                if followed.seq > seen {
                    lost = None;
                }
                let since = *lost.get_or_insert_with(|| {
                    eprintln!(
                        "lost the server ({e}); reconnecting for up to {} s: the job goes on there",
                        RECONNECT.as_secs()
                    );
                    Instant::now()
                });
                if since.elapsed() > RECONNECT {
                    return Err(e).with_context(|| {
                        format!("watching job {job_id}; it may still be running: `udapose jobs watch {job_id} --after-seq {}` follows it", followed.seq)
                    });
                }
                tokio::time::sleep(Duration::from_secs(1)).await;
            }
            Err(e) => return Err(e).with_context(|| format!("watching job {job_id}")),
        }
    }
    let Some(last) = followed.last.filter(|e| is_terminal(e.state)) else {
        bail!("job {job_id}'s events ended before the job did");
    };
    // The job's reason (e.g. the failed criteria) and version; the event's if it cannot be read.
    let (version, reason) = match client.get_job(job_id).await {
        Ok(job) if job.state == last.state => {
            let reason = if job.reason.is_empty() { last.message.clone() } else { job.reason };
            let version = if job.version.is_empty() { last.version.clone() } else { job.version };
            (version, reason)
        }
        _ => (last.version.clone(), last.message.clone()),
    };
    if json {
        println!("{}", output::result_json(job_id, last.state, &version, &reason)?);
    } else {
        println!("{}", output::final_line(job_id, last.state, &version, &reason));
    }
    Ok(if last.state == JobState::Activated as i32 { ExitCode::SUCCESS } else { ExitCode::from(JOB_NOT_ACTIVATED) })
}

/// What `watch` has printed: it resumes after `seq` when it reconnects.
struct Followed {
    seq: u64,
    last: Option<JobEvent>,
    gate: Vec<GateCriterion>,
}

impl Followed {
    /// Prints the job's events after `seq` until the stream ends.
    async fn until_end(&mut self, client: &Client, job_id: &str, json: bool) -> Result<(), ClientError> {
        let mut events = client.watch_job(job_id, self.seq).await?;
        while let Some(event) = events.message().await? {
            if json {
                let event = output::event_json(&event).map_err(|e| ClientError::Protocol(e.to_string()))?;
                println!("{}", json!({ "event": event }));
            } else {
                println!("{}", output::event_line(&event));
                if !event.gate.is_empty() && event.gate != self.gate {
                    event.gate.iter().for_each(|c| println!("{}", output::gate_line(c)));
                    self.gate = event.gate.clone();
                }
            }
            self.seq = event.seq;
            self.last = Some(event);
        }
        Ok(())
    }
}
