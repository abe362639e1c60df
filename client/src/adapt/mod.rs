//! Online adaptation: uploading target images over `StreamTargets` (resending what a broken
//! stream or a full buffer left unacknowledged), and adaptation jobs (start, watch with
//! reconnection, get, list, cancel).

use std::{
    collections::{BTreeMap, VecDeque},
    pin::Pin,
    time::Duration,
};

use sha2::{Digest, Sha256};
use tokio::sync::mpsc;
use tokio_stream::{Stream, StreamExt, wrappers::ReceiverStream};
use tonic::{Status, Streaming};
use udapose_proto::v1::{
    AdaptOverrides, CancelJobRequest, GetJobRequest, Job, JobEvent, JobState, ListJobsRequest,
    ListRegressionSetsRequest, RegressionSet, StartJobRequest, TargetAck, TargetImage, WatchJobRequest,
    adaptation_service_client::AdaptationServiceClient, target_ack,
};

use crate::{Client, Error, MAX_BUFFER_FULL_BACKOFF, Replies, Tries};

/// Images sent on a `StreamTargets` stream and not yet acknowledged, at most: the server acks
/// each once it is durable, so a few in flight hide the round trip and the fsync.
const WINDOW: usize = 8;
/// How long to wait for the server to end a stream once every image has its ack.
const CLOSE_TIMEOUT: Duration = Duration::from_secs(2);

/// The outcome of one uploaded image: its final ack (ACCEPTED, DUPLICATE, or REJECTED with a
/// reason; BUFFER_FULL only once the resends allowed are spent).
#[derive(Debug, Clone, PartialEq)]
pub struct Upload {
    /// The name the caller gave the image (e.g. its file name).
    pub name: String,
    pub ack: TargetAck,
    /// How many times the image was sent (1 unless a broken stream or a full buffer made us
    /// resend it).
    pub sends: u32,
}

/// The uploads of [`Client::stream_targets`], one per image, in the order the images were given.
/// Ends after the last image's upload, or after an `Err` (the images after it were not all
/// acknowledged).
pub type Uploads = Replies<Upload>;

/// A job's events from [`Client::watch_job`], in `seq` order, without gaps or repeats across
/// reconnections. Ends after the terminal event, or after an `Err`.
pub type JobEvents = Replies<JobEvent>;

/// A state a job never leaves: ACTIVATED, REJECTED, SUPERSEDED, FAILED or CANCELLED.
pub fn is_terminal(state: i32) -> bool {
    matches!(
        JobState::try_from(state),
        Ok(JobState::Activated | JobState::Rejected | JobState::Superseded | JobState::Failed | JobState::Cancelled)
    )
}

/// The proto name of a job state (`"ACTIVATED"`), or `"UNKNOWN(<n>)"` for a value this client
/// does not know.
pub fn state_name(state: i32) -> String {
    match JobState::try_from(state) {
        Ok(s) => s.as_str_name().to_owned(),
        Err(_) => format!("UNKNOWN({state})"),
    }
}

/// The server rejected the image only because the category's buffer is full (worth resending
/// once a job has used buffered images).
pub fn buffer_full(ack: &TargetAck) -> bool {
    ack.status == target_ack::Status::Rejected as i32 && ack.rejection == target_ack::Rejection::BufferFull as i32
}

/// A fresh random id for [`Client::start_job`], which makes the call safe to retry.
pub fn new_client_job_id() -> String {
    format!("cli-{:032x}", rand::random::<u128>())
}

impl Client {
    /// Uploads target images of `category` over one `StreamTargets` stream (reopened when it
    /// breaks) and yields one [`Upload`] per image, in the order given, once its ack is final.
    ///
    /// Images are read from `images` only as the stream can take them (a few are in flight);
    /// each is kept until acknowledged. When the stream breaks or the server is UNAVAILABLE, the
    /// images not yet acknowledged are resent on a new stream (harmless: an image's id is its
    /// sha256, so one already stored comes back DUPLICATE), at most `retries` times in a row
    /// without progress. Images REJECTED with BUFFER_FULL are resent after a pause that grows
    /// per resend (`buffer_full_backoff`), at most `buffer_full_retries` times each; no new
    /// image is sent meanwhile. Other rejections (invalid image, unknown category) are final.
    ///
    /// Spawns its work on the current tokio runtime. Dropping the [`Uploads`] stops it.
    ///
    /// ```no_run
    /// # async fn run(client: udapose_client::Client) -> Result<(), udapose_client::Error> {
    /// let images = vec![("a.png".to_owned(), std::fs::read("a.png").unwrap())];
    /// let mut uploads = client.stream_targets("car", tokio_stream::iter(images));
    /// while let Some(upload) = uploads.message().await? {
    ///     println!("{}: {:?} {}", upload.name, upload.ack.status(), upload.ack.reason);
    /// }
    /// # Ok(())
    /// # }
    /// ```
    pub fn stream_targets<S>(&self, category: &str, images: S) -> Uploads
    where
        S: Stream<Item = (String, Vec<u8>)> + Send + 'static,
    {
        self.stream(category, false, images)
    }

    /// Like [`Client::stream_targets`], into the category's anchor set instead of its
    /// adaptation buffer: images of the conditions the model must keep handling, a regression
    /// set the gate guards for every later job (no job trains on them; at most 128).
    pub fn stream_anchors<S>(&self, category: &str, images: S) -> Uploads
    where
        S: Stream<Item = (String, Vec<u8>)> + Send + 'static,
    {
        self.stream(category, true, images)
    }

    fn stream<S>(&self, category: &str, anchor: bool, images: S) -> Uploads
    where
        S: Stream<Item = (String, Vec<u8>)> + Send + 'static,
    {
        let (out, rx) = mpsc::channel(2 * WINDOW);
        let (client, category) = (self.clone(), category.to_owned());
        tokio::spawn(async move {
            if let Err(e) = upload(&client, &category, anchor, Box::pin(images), &out).await {
                let _ = out.send(Err(e)).await;
            }
        });
        Replies::new(rx)
    }

    /// Starts an adaptation job on the category's unused buffered images, or returns the job
    /// already queued or running for it. With `client_job_id` (see [`new_client_job_id`]) the
    /// call is idempotent and retried on UNAVAILABLE; without, it is sent once.
    pub async fn start_job(
        &self,
        category: &str,
        overrides: AdaptOverrides,
        client_job_id: Option<&str>,
    ) -> Result<Job, Error> {
        let message = &StartJobRequest {
            category: category.into(),
            overrides: Some(overrides),
            client_job_id: client_job_id.unwrap_or_default().into(),
        };
        let call = |ch| async move { AdaptationServiceClient::new(ch).start_job(self.request(message.clone())).await };
        let response = match client_job_id {
            Some(id) if !id.is_empty() => self.retrying(call).await?,
            _ => self.once(call).await?,
        };
        Ok(response.into_inner())
    }

    /// The job's events after `after_seq` (0: all), then new ones as they happen, until the
    /// terminal one. The first call's error (e.g. NOT_FOUND) is returned here; later, when the
    /// stream breaks (or ends before the terminal event) it is reopened from the last `seq`
    /// seen (on the next endpoint up), at most `retries` pauses in a row without an event.
    pub async fn watch_job(&self, job_id: &str, after_seq: u64) -> Result<JobEvents, Error> {
        let message = &WatchJobRequest { job_id: job_id.into(), after_seq };
        let call = |ch| async move { AdaptationServiceClient::new(ch).watch_job(self.request(message.clone())).await };
        let (endpoint, response) = self.retrying_on(call).await?;
        let stream = (endpoint, response.into_inner());
        let (out, rx) = mpsc::channel(16);
        let (client, job_id) = (self.clone(), job_id.to_owned());
        tokio::spawn(async move {
            if let Err(e) = follow(&client, &job_id, after_seq, stream, &out).await {
                let _ = out.send(Err(e)).await;
            }
        });
        Ok(Replies::new(rx))
    }

    /// One job, with its last event.
    pub async fn get_job(&self, job_id: &str) -> Result<Job, Error> {
        let message = &GetJobRequest { job_id: job_id.into() };
        let response = self
            .retrying(|ch| async move { AdaptationServiceClient::new(ch).get_job(self.request(message.clone())).await })
            .await?;
        Ok(response.into_inner())
    }

    /// Jobs, newest first; only `category`'s when given.
    pub async fn list_jobs(&self, category: Option<&str>) -> Result<Vec<Job>, Error> {
        let message = &ListJobsRequest { category: category.unwrap_or_default().into() };
        let response = self
            .retrying(
                |ch| async move { AdaptationServiceClient::new(ch).list_jobs(self.request(message.clone())).await },
            )
            .await?;
        Ok(response.into_inner().jobs)
    }

    /// The category's regression sets (what the gate guards besides a job's own held-out
    /// images), oldest first.
    pub async fn list_regression_sets(&self, category: &str) -> Result<Vec<RegressionSet>, Error> {
        let message = &ListRegressionSetsRequest { category: category.into() };
        let response = self
            .retrying(|ch| async move {
                AdaptationServiceClient::new(ch).list_regression_sets(self.request(message.clone())).await
            })
            .await?;
        Ok(response.into_inner().sets)
    }

    /// Stops a queued or running job (CANCELLED); a finished job comes back unchanged. Sent
    /// once (not in the contract's list of retried calls).
    pub async fn cancel_job(&self, job_id: &str, reason: &str) -> Result<Job, Error> {
        let message = CancelJobRequest { job_id: job_id.into(), reason: reason.into() };
        let call = |ch| async move { AdaptationServiceClient::new(ch).cancel_job(self.request(message)).await };
        Ok(self.once(call).await?.into_inner())
    }
}

/// Drives the uploads of [`Client::stream_targets`]; `Ok` once every image has its upload (or
/// the caller went away).
async fn upload(
    client: &Client,
    category: &str,
    anchor: bool,
    mut images: Images,
    out: &mpsc::Sender<Result<Upload, Error>>,
) -> Result<(), Error> {
    let mut ledger = Ledger::new(client.buffer_full_retries, client.buffer_full_backoff);
    ledger.anchor = anchor;
    let mut input_done = false;
    let mut tries = Tries::default();
    loop {
        // A stream is opened with images already queued on it (so a server that reads the
        // first image before it answers works as well as one that answers at once).
        if ledger.is_idle() {
            if input_done {
                return Ok(());
            }
            match next_image(&mut images, out).await {
                None => return Ok(()),
                Some(Some((name, bytes))) => ledger.admit(name, bytes),
                Some(None) => {
                    input_done = true;
                    continue;
                }
            }
        }
        let (tx, rx) = mpsc::channel::<TargetImage>(WINDOW);
        // Never blocks: the channel holds a window.
        fill_window(&mut ledger, category, &tx).await;
        let (endpoint, channel) = client.pool.pick();
        let targets = client.request(ReceiverStream::new(rx));
        let opened = AdaptationServiceClient::new(channel).stream_targets(targets).await;
        let broken = match opened {
            Err(status) => status,
            Ok(response) => {
                client.pool.answered(endpoint);
                let mut acks = response.into_inner();
                loop {
                    fill_window(&mut ledger, category, &tx).await;
                    let want_input = !input_done && ledger.window_open() && !ledger.has_to_send();
                    if !ledger.has_in_flight() && !want_input {
                        if input_done && ledger.is_idle() {
                            drop(tx);
                            let _ = tokio::time::timeout(CLOSE_TIMEOUT, async {
                                while let Ok(Some(_)) = acks.message().await {}
                            })
                            .await;
                            return Ok(());
                        }
                        continue;
                    }
                    tokio::select! {
                        biased;
                        () = out.closed() => return Ok(()),
                        ack = acks.message(), if ledger.has_in_flight() => match ack {
                            Ok(Some(ack)) => {
                                tries = Tries::default();
                                ledger.acked(ack)?;
                                for done in ledger.take_ready() {
                                    if out.send(Ok(done)).await.is_err() {
                                        return Ok(());
                                    }
                                }
                            }
                            Ok(None) => {
                                break Status::unavailable("the server ended the stream before acknowledging every image")
                            }
                            Err(status) => break status,
                        },
                        image = images.next(), if want_input => match image {
                            Some((name, bytes)) => ledger.admit(name, bytes),
                            None => input_done = true,
                        },
                    }
                }
            }
        };
        ledger.broken();
        client.again(&mut tries, endpoint, broken).await?;
    }
}

/// The caller's images, named, as [`Client::stream_targets`] takes them.
type Images = Pin<Box<dyn Stream<Item = (String, Vec<u8>)> + Send>>;

/// Waits out the ledger's pause, then queues on `tx` what the window allows.
async fn fill_window(ledger: &mut Ledger, category: &str, tx: &mpsc::Sender<TargetImage>) {
    if let Some(pause) = ledger.pause() {
        tokio::time::sleep(pause).await;
        ledger.release_waiting();
    }
    while ledger.window_open() {
        let Some(image) = ledger.send_next(category) else { break };
        // An error means the call is over; reading the acks says why.
        if tx.send(image).await.is_err() {
            break;
        }
    }
}

/// The caller's next image (`Some(None)`: its input ended), or `None` when it went away.
async fn next_image(
    images: &mut Images,
    out: &mpsc::Sender<Result<Upload, Error>>,
) -> Option<Option<(String, Vec<u8>)>> {
    tokio::select! {
        biased;
        () = out.closed() => None,
        image = images.next() => Some(image),
    }
}

/// Drives [`Client::watch_job`]: forwards events, reopens the stream after the last seq seen.
async fn follow(
    client: &Client,
    job_id: &str,
    after_seq: u64,
    (mut endpoint, mut stream): (usize, Streaming<JobEvent>),
    out: &mpsc::Sender<Result<JobEvent, Error>>,
) -> Result<(), Error> {
    let mut last = after_seq;
    let mut tries = Tries::default();
    loop {
        let broken = loop {
            let message = tokio::select! {
                biased;
                () = out.closed() => return Ok(()),
                message = stream.message() => message,
            };
            match message {
                Ok(Some(event)) => {
                    tries = Tries::default();
                    if event.seq <= last {
                        continue; // already seen (a server replaying from an older seq)
                    }
                    last = event.seq;
                    let terminal = is_terminal(event.state);
                    if out.send(Ok(event)).await.is_err() || terminal {
                        return Ok(());
                    }
                }
                Ok(None) => {
                    break Status::unavailable("the server ended the job's event stream before its terminal event");
                }
                Err(status) => break status,
            }
        };
        // Reopened after the last event seen, on the next endpoint up.
        let mut status = broken;
        loop {
            client.again(&mut tries, endpoint, status).await?;
            let channel;
            (endpoint, channel) = client.pool.pick();
            let message = WatchJobRequest { job_id: job_id.into(), after_seq: last };
            match AdaptationServiceClient::new(channel).watch_job(client.request(message)).await {
                Ok(response) => {
                    client.pool.answered(endpoint);
                    stream = response.into_inner();
                    break;
                }
                Err(s) => status = s,
            }
        }
    }
}

/// An image on its way, kept (bytes included) until its ack is final.
#[derive(Debug)]
struct Pending {
    /// Position in the caller's sequence.
    index: usize,
    name: String,
    image: Vec<u8>,
    sha256: String,
    sends: u32,
    /// BUFFER_FULL rejections so far.
    full: u32,
}

/// The bookkeeping of [`Client::stream_targets`], apart from any I/O: which images are to be
/// sent, in flight on the current stream (acks come in send order), waiting for buffer space,
/// or done and waiting for their turn to be yielded in the caller's order.
#[derive(Debug)]
struct Ledger {
    max_full: u32,
    full_backoff: Duration,
    next_index: usize,
    to_send: VecDeque<Pending>,
    in_flight: VecDeque<Pending>,
    /// Rejected with BUFFER_FULL; resent after a pause, once nothing is in flight.
    waiting: Vec<Pending>,
    done: BTreeMap<usize, Upload>,
    next_ready: usize,
    /// Whether the images go to the anchor set (`TargetImage.anchor`).
    anchor: bool,
}

impl Ledger {
    fn new(max_full: u32, full_backoff: Duration) -> Self {
        Ledger {
            max_full,
            full_backoff,
            next_index: 0,
            to_send: VecDeque::new(),
            in_flight: VecDeque::new(),
            waiting: Vec::new(),
            done: BTreeMap::new(),
            anchor: false,
            next_ready: 0,
        }
    }

    /// A new image from the caller, queued to be sent.
    fn admit(&mut self, name: String, image: Vec<u8>) {
        let sha256 = format!("{:x}", Sha256::digest(&image));
        self.to_send.push_back(Pending { index: self.next_index, name, image, sha256, sends: 0, full: 0 });
        self.next_index += 1;
    }

    /// Whether another image may go out: the window has room and no image waits for buffer
    /// space (while one does, sending more would only be rejected too).
    fn window_open(&self) -> bool {
        self.in_flight.len() < WINDOW && self.waiting.is_empty()
    }

    fn has_to_send(&self) -> bool {
        !self.to_send.is_empty()
    }

    fn has_in_flight(&self) -> bool {
        !self.in_flight.is_empty()
    }

    /// Nothing left to send, await or resend.
    fn is_idle(&self) -> bool {
        self.to_send.is_empty() && self.in_flight.is_empty() && self.waiting.is_empty()
    }

    /// The next message to send; the image moves in flight.
    fn send_next(&mut self, category: &str) -> Option<TargetImage> {
        let mut pending = self.to_send.pop_front()?;
        pending.sends += 1;
        let message = TargetImage { category: category.into(), image: pending.image.clone(), anchor: self.anchor };
        self.in_flight.push_back(pending);
        Some(message)
    }

    /// The ack of the oldest image in flight.
    fn acked(&mut self, ack: TargetAck) -> Result<(), Error> {
        let Some(mut pending) = self.in_flight.pop_front() else {
            return Err(Error::Protocol(format!("an ack ({}) for no image in flight", ack.sha256)));
        };
        if !ack.sha256.is_empty() && !ack.sha256.eq_ignore_ascii_case(&pending.sha256) {
            return Err(Error::Protocol(format!(
                "ack for sha256 {} where {} ({}) was next",
                ack.sha256, pending.sha256, pending.name
            )));
        }
        if buffer_full(&ack) && pending.full < self.max_full {
            pending.full += 1;
            self.waiting.push(pending);
            return Ok(());
        }
        let upload = Upload { name: pending.name, ack, sends: pending.sends };
        self.done.insert(pending.index, upload);
        Ok(())
    }

    /// The stream broke: every image in flight is to be sent again, first.
    fn broken(&mut self) {
        while let Some(pending) = self.in_flight.pop_back() {
            self.to_send.push_front(pending);
        }
    }

    /// How long to pause before resending the images rejected with BUFFER_FULL, once nothing is
    /// in flight (their acks might add to the waiting ones): the backoff of the image rejected
    /// most often.
    fn pause(&self) -> Option<Duration> {
        if !self.in_flight.is_empty() {
            return None;
        }
        let most = self.waiting.iter().map(|p| p.full).max()?;
        let backoff = self.full_backoff.saturating_mul(2u32.saturating_pow(most.saturating_sub(1)));
        Some(backoff.min(MAX_BUFFER_FULL_BACKOFF))
    }

    /// After the pause: the waiting images are sent next, in the caller's order.
    fn release_waiting(&mut self) {
        self.to_send.extend(self.waiting.drain(..));
        self.to_send.make_contiguous().sort_by_key(|p| p.index);
    }

    /// Uploads whose turn has come (every earlier image has one), in order.
    fn take_ready(&mut self) -> Vec<Upload> {
        let mut ready = Vec::new();
        while let Some(upload) = self.done.remove(&self.next_ready) {
            ready.push(upload);
            self.next_ready += 1;
        }
        ready
    }
}

#[cfg(test)]
mod tests;
