//! Video over `EstimateStream`: frames are kept until answered, so that when the stream breaks
//! (its server died, or went away) the unanswered ones are resent, in order, on a new stream to
//! the next endpoint up. Estimates are idempotent, so a frame answered twice costs only time;
//! the caller sees each answer once.

use std::{collections::VecDeque, pin::Pin, time::Duration};

use tokio::sync::mpsc;
use tokio_stream::{Stream, StreamExt, wrappers::ReceiverStream};
use tonic::{Status, Streaming};
use udapose_proto::v1::{EstimateRequest, EstimateResponse, pose_service_client::PoseServiceClient};

use crate::{Client, Error, Replies, Tries};

/// Frames sent and not yet answered, at most: enough to hide the round trip, few enough to
/// keep (and resend) cheaply. The caller's stream is read no faster.
const WINDOW: usize = 8;
/// How long to wait for the server to end the stream once every frame has its answer.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(2);

/// The answers of [`Client::estimate_stream`], one per frame, in order. Ends after the last
/// frame's answer, or after an `Err`.
pub type Estimates = Replies<EstimateResponse>;

type Frames = Pin<Box<dyn Stream<Item = EstimateRequest> + Send>>;

impl Client {
    /// Streams frames; one answer per frame, in order. Failed frames carry `error`. When the
    /// stream breaks or the server is UNAVAILABLE, the frames not yet answered are resent on a
    /// new stream (to another endpoint when one is up; see the crate's documentation). Errors,
    /// a refusal to open the stream included, come as the stream's last item.
    ///
    /// Spawns its work on the current tokio runtime. Dropping the [`Estimates`] stops it.
    pub async fn estimate_stream(
        &self,
        frames: impl Stream<Item = EstimateRequest> + Send + 'static,
    ) -> Result<Estimates, Error> {
        let (out, rx) = mpsc::channel(WINDOW);
        let client = self.clone();
        tokio::spawn(async move {
            if let Err(e) = relay(&client, Box::pin(frames), &out).await {
                let _ = out.send(Err(e)).await;
            }
        });
        Ok(Replies::new(rx))
    }
}

/// The frames sent on the current stream and not yet answered, oldest first, and whether the
/// caller's frames have ended.
#[derive(Default)]
struct Pending {
    frames: VecDeque<EstimateRequest>,
    input_done: bool,
}

/// Drives [`Client::estimate_stream`]: opens streams, one at a time, until every frame has its
/// answer (`Ok`, also when the caller went away).
async fn relay(
    client: &Client,
    mut frames: Frames,
    out: &mpsc::Sender<Result<EstimateResponse, Error>>,
) -> Result<(), Error> {
    let mut pending = Pending::default();
    let mut tries = Tries::default();
    loop {
        // A stream is opened with a frame on it (a server may read one before it answers).
        if pending.frames.is_empty() {
            if pending.input_done {
                return Ok(());
            }
            let frame = tokio::select! {
                biased;
                () = out.closed() => return Ok(()),
                frame = frames.next() => frame,
            };
            let Some(frame) = frame else { return Ok(()) };
            pending.frames.push_back(frame);
        }
        let (endpoint, channel) = client.pool.pick();
        let (tx, rx) = mpsc::channel(WINDOW);
        for frame in &pending.frames {
            let _ = tx.try_send(frame.clone()); // never full: the channel holds a window
        }
        let status =
            match PoseServiceClient::new(channel).estimate_stream(client.request(ReceiverStream::new(rx))).await {
                Err(status) => status,
                Ok(answers) => {
                    client.pool.answered(endpoint);
                    match forward(answers.into_inner(), tx, &mut frames, &mut pending, &mut tries, out).await {
                        Ok(()) => return Ok(()),
                        Err(status) => status,
                    }
                }
            };
        client.again(&mut tries, endpoint, status).await?;
    }
}

/// Sends the caller's frames on one stream and passes its answers on, until every frame has
/// one (`Ok`) or the stream breaks (`Err`: why).
async fn forward(
    mut answers: Streaming<EstimateResponse>,
    tx: mpsc::Sender<EstimateRequest>,
    frames: &mut Frames,
    pending: &mut Pending,
    tries: &mut Tries,
    out: &mpsc::Sender<Result<EstimateResponse, Error>>,
) -> Result<(), Status> {
    loop {
        if pending.input_done && pending.frames.is_empty() {
            // Our end of the stream ends; the server's should follow.
            drop(tx);
            let _ =
                tokio::time::timeout(CLOSE_TIMEOUT, async { while let Ok(Some(_)) = answers.message().await {} }).await;
            return Ok(());
        }
        let want_frame = !pending.input_done && pending.frames.len() < WINDOW;
        tokio::select! {
            biased;
            () = out.closed() => return Ok(()),
            answer = answers.message(), if !pending.frames.is_empty() => match answer? {
                Some(answer) => {
                    pending.frames.pop_front();
                    *tries = Tries::default();
                    if out.send(Ok(answer)).await.is_err() {
                        return Ok(());
                    }
                }
                None => return Err(Status::unavailable("the server ended the stream before answering every frame")),
            },
            frame = frames.next(), if want_frame => match frame {
                Some(frame) => {
                    pending.frames.push_back(frame.clone());
                    // An error means the call is over; reading the answers says why.
                    let _ = tx.send(frame).await;
                }
                None => pending.input_done = true,
            },
        }
    }
}
