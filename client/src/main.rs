//! `udapose`: command-line client for a udapose server (gRPC).

mod follow;
mod inputs;
mod output;

use std::{path::PathBuf, process::ExitCode};

use anyhow::{Context, Result, bail};
use clap::{Args, Parser, Subcommand};
use inputs::{expand, parse_box, read_input};
use serde_json::{Value, json};
use udapose_client::{BoundingBox, Client, ClientOptions, ModelInfo};
use udapose_proto::v1::{EstimateRequest, EstimateResponse, estimate_request::Input};

/// The exit status when a followed job ended other than ACTIVATED.
const JOB_NOT_ACTIVATED: u8 = 3;

const ADAPT_HELP: &str = "\
Output (stdout, one line each; stable, for scripts):
  uploaded <N> images to <CATEGORY>: <A> accepted, <D> duplicate, <R> rejected (buffer <B>/<CAP>)
  rejected <IMAGE>: <REASON>             one per rejected image (REASON: CODE: explanation)
  job <ID> <STATE> category <CATEGORY> from <SOURCE_VERSION> (generation <G>)
                                         the job StartJob returned (the last line with --no-follow)
  #<SEQ> <STATE> round <R>/<MAX> fired <F> change <DEG>° used <U> held-out <H> eta <ETA>[ version <V>][: <MESSAGE>]
                                         one per job event (change -: no previous round; eta -: unknown)
    gate <CRITERION> active <A> candidate <C> threshold <T> passed|FAILED[ (<DETAIL>)]
                                         the validation gate's criteria, when they change
  job <ID> ACTIVATED version <VERSION>   the last line when the job activated its model
  job <ID> <STATE>: <REASON>             the last line when it ended REJECTED, SUPERSEDED, FAILED
                                         or CANCELLED
The progress bar goes to stderr (only on a terminal). With --json, stdout holds one JSON object
per line instead: {\"uploads\": ...}, {\"job\": ...}, {\"event\": ...} per event, then
{\"result\": {\"job_id\", \"state\", \"version\", \"reason\"}}.

Images that met a full buffer (BUFFER_FULL) are resent after a growing pause, and images a
broken connection left unacknowledged are resent (an image's id is its sha256: a resend is a
DUPLICATE). If a job of the category is already queued or running, StartJob returns it.
Following the job, a lost server (restarting, say: the job survives and resumes there) is
reconnected to for up to 120 s, from the last event seen; a note goes to stderr.

Exit status: 0 the job was ACTIVATED (or, with --no-follow, started); 3 it ended otherwise;
1 any other error, with one line on stderr: `udapose: error: <what>: <gRPC code>: <message>`.";

const WATCH_HELP: &str = "\
Output: one `#<SEQ> <STATE> ...` line per event and `gate ...` lines as for `udapose adapt`, then
`job <ID> ACTIVATED version <VERSION>` or `job <ID> <STATE>: <REASON>`; --json: {\"event\": ...}
lines, then {\"result\": ...}. A lost server is reconnected to for up to 120 s, from the last
event seen. Exit status: 0 ACTIVATED, 3 another terminal state, 1 an error.";

/// Talk to a udapose pose-estimation server over gRPC.
#[derive(Debug, Parser)]
#[command(version)]
struct Cli {
    /// The server's gRPC address(es): `host:port` or `http(s)://host:port`, comma-separated (or
    /// repeated) for replicas. Calls go to each endpoint up in turn; one that is unreachable or
    /// UNAVAILABLE is passed over for 1 s (doubled per failure in a row, at most 10 s), then tried
    /// again. A call safe to repeat fails over to the next endpoint at once, and a broken stream
    /// reopens there.
    #[arg(
        long,
        visible_alias = "endpoint",
        env = "UDAPOSE_ENDPOINT",
        default_value = "127.0.0.1:50051",
        global = true,
        value_delimiter = ','
    )]
    endpoints: Vec<String>,
    /// Bearer token.
    #[arg(long, env = "UDAPOSE_TOKEN", hide_env_values = true, global = true)]
    token: Option<String>,
    /// PEM CA certificate to trust for TLS (implies TLS).
    #[arg(long, value_name = "PEM", global = true)]
    ca_cert: Option<PathBuf>,
    /// Name to verify the server's certificate against (default: the endpoint's host).
    #[arg(long, global = true)]
    tls_domain: Option<String>,
    /// Retries, with backoff, of a call that every endpoint answered UNAVAILABLE (overloaded) or
    /// could not take (network), only for calls that are safe to repeat; for a stream,
    /// reconnections in a row without progress.
    #[arg(long, default_value_t = 4, global = true)]
    retries: u32,
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// List the server's models: category, version being served, and whether it is ready;
    /// `models versions|activate|rollback` manage a category's versions.
    Models {
        /// Print JSON (`{"models": [...]}`, or the subcommand's object) instead of a table.
        #[arg(long, global = true)]
        json: bool,
        #[command(subcommand)]
        action: Option<ModelsCommand>,
    },
    /// Describe one category's model (version, generation, backbone, crop, provenance).
    Describe { category: String },
    /// Estimate the pose in images: files, folders (their PNG/JPEG/WebP files), or `-` (stdin).
    Estimate {
        #[arg(long, default_value = "car")]
        category: String,
        /// A detection box `x0,y0,x1,y1` in image pixels (repeat for several objects); none:
        /// each image is the object's crop.
        #[arg(long, value_parser = parse_box)]
        bbox: Vec<BoundingBox>,
        /// One JSON object per image (as the HTTP API answers) instead of a table.
        #[arg(long)]
        json: bool,
        #[arg(required = true)]
        images: Vec<PathBuf>,
    },
    /// Online adaptation: upload a folder's images as unlabelled target images of a category,
    /// start an adaptation job, and follow it until its model is activated or not.
    #[command(after_long_help = ADAPT_HELP)]
    Adapt(AdaptArgs),
    /// Adaptation jobs: list, get, watch, cancel.
    Jobs {
        /// Print JSON instead of text.
        #[arg(long, global = true)]
        json: bool,
        #[command(subcommand)]
        action: JobsCommand,
    },
}

#[derive(Debug, Subcommand)]
enum ModelsCommand {
    /// A category's versions (VERSION ACTIVE TRAINED_AS JOB) and its activation log, newest first
    /// (GENERATION VERSION PREVIOUS ACTOR TIME REASON).
    Versions { category: String },
    /// Make VERSION the active one. Prints `activated <CATEGORY> version <V> generation <G>
    /// (previous <P>)`.
    Activate {
        category: String,
        version: String,
        /// Recorded in the activation log.
        #[arg(long, default_value = "")]
        reason: String,
        /// Activate only if this is the active generation (ABORTED otherwise); makes the call
        /// safe to retry.
        #[arg(long, value_name = "G")]
        expected_generation: Option<u64>,
    },
    /// Re-activate the version that was active before the current one. Prints `rolled back
    /// <CATEGORY> version <V> generation <G> (previous <P>)`.
    Rollback {
        category: String,
        /// Recorded in the activation log.
        #[arg(long, default_value = "")]
        reason: String,
        /// Roll back only if this is the active generation (ABORTED otherwise); makes the call
        /// safe to retry.
        #[arg(long, value_name = "G")]
        expected_generation: Option<u64>,
    },
}

#[derive(Debug, Subcommand)]
enum JobsCommand {
    /// Jobs, newest first: JOB CATEGORY STATE ROUND IMAGES(used+held out) VERSION UPDATED REASON.
    List {
        /// Only this category's jobs.
        #[arg(long)]
        category: Option<String>,
    },
    /// One job in detail, with its last event.
    Get { id: String },
    /// The regression sets the gate guards for a category (SET KIND VERSION IMAGES CREATED):
    /// the held-out images of every activated job and the anchor images, oldest first.
    Sets { category: String },
    /// Follow a job's events until it ends.
    #[command(after_long_help = WATCH_HELP)]
    Watch {
        id: String,
        /// Only the events after this sequence number (0: all).
        #[arg(long, default_value_t = 0)]
        after_seq: u64,
    },
    /// Stop a queued or running job (CANCELLED). Answers once the job has stopped (a running
    /// one stops at its next progress report, within seconds; at most 30 s are waited) and
    /// prints `job <ID> CANCELLED: <REASON>`; the job's images leave the buffer and may be
    /// uploaded again. A job that had already ended is left as it was and printed as `udapose
    /// adapt` does.
    Cancel {
        id: String,
        /// Recorded with the job.
        #[arg(long, default_value = "")]
        reason: String,
    },
}

#[derive(Debug, Args)]
struct AdaptArgs {
    /// The object category the images show (e.g. car).
    #[arg(long)]
    category: String,
    /// A folder of PNG/JPEG/WebP images (not its subfolders), uploaded in name order.
    #[arg(long, value_name = "DIR")]
    images: PathBuf,
    /// Keep the images in the category's anchor set instead, and start no job: conditions the
    /// model must keep handling, which the gate guards for every later job (no job trains on
    /// them; at most 128 per category). See them with `udapose jobs sets CATEGORY`.
    #[arg(long)]
    anchor: bool,
    /// Print the job and exit once it is started, without following it.
    #[arg(long)]
    no_follow: bool,
    /// Most EM rounds of the job (default: the server's).
    #[arg(long, value_name = "N")]
    max_rounds: Option<u32>,
    /// The job's learning rate (default: the server's).
    #[arg(long, value_name = "X")]
    learning_rate: Option<f64>,
    /// The job's random seed (default: the server's).
    #[arg(long, value_name = "N")]
    seed: Option<u64>,
    /// The id that makes StartJob idempotent (default: a fresh random one): run the command
    /// again with the same id to get the same job.
    #[arg(long)]
    client_job_id: Option<String>,
    /// How often an image rejected with BUFFER_FULL is resent, after a pause of 1 s doubled
    /// per resend (at most 30 s), before its rejection is final.
    #[arg(long, default_value_t = 6, value_name = "N")]
    buffer_full_retries: u32,
    /// One JSON object per line instead of text.
    #[arg(long)]
    json: bool,
}

#[tokio::main]
async fn main() -> ExitCode {
    match run(Cli::parse()).await {
        Ok(code) => code,
        Err(e) => {
            // One line: the context, then the cause (an RPC's: `<gRPC code>: <message>`).
            eprintln!("udapose: error: {e:#}");
            ExitCode::FAILURE
        }
    }
}

async fn run(cli: Cli) -> Result<ExitCode> {
    let ca_cert = match &cli.ca_cert {
        Some(p) => Some(std::fs::read(p).with_context(|| format!("reading {}", p.display()))?),
        None => None,
    };
    let options = ClientOptions {
        endpoints: cli.endpoints.clone(),
        token: cli.token.clone(),
        ca_cert,
        tls_domain: cli.tls_domain.clone(),
        retries: cli.retries,
        ..ClientOptions::new("")
    };
    let options = match &cli.command {
        Command::Adapt(a) => ClientOptions { buffer_full_retries: a.buffer_full_retries, ..options },
        _ => options,
    };
    let client = Client::connect_with(options).await.context("connecting")?;
    match cli.command {
        Command::Models { json, action: Some(action) } => models_command(&client, action, json).await?,
        Command::Models { json, action: None } => {
            let models = client.list_models().await.context("listing models")?;
            if json {
                println!("{}", models_json(&models));
            } else {
                print_table(&models);
            }
        }
        Command::Describe { category } => {
            let d = client.describe_model(&category).await.with_context(|| format!("describing {category}"))?;
            let out = udapose_api::ModelDescription::from(d);
            println!("{}", serde_json::to_string_pretty(&out)?);
        }
        Command::Estimate { category, bbox, json, images } => {
            estimate(&client, &category, &bbox, json, &images).await?
        }
        Command::Adapt(args) => return follow::adapt(&client, args).await,
        Command::Jobs { json, action } => return jobs_command(&client, action, json).await,
    }
    Ok(ExitCode::SUCCESS)
}

async fn models_command(client: &Client, action: ModelsCommand, json: bool) -> Result<()> {
    match action {
        ModelsCommand::Versions { category } => {
            let v = client.list_versions(&category).await.with_context(|| format!("listing {category}'s versions"))?;
            if json {
                println!("{}", output::versions_json(&v));
            } else {
                output::versions_lines(&v).iter().for_each(|l| println!("{l}"));
            }
        }
        ModelsCommand::Activate { category, version, reason, expected_generation } => {
            let entry = client
                .activate(&category, &version, &reason, expected_generation)
                .await
                .with_context(|| format!("activating {category} version {version}"))?;
            if json {
                println!("{}", output::activation_json(&entry));
            } else {
                println!("{}", output::activation_line("activated", &entry));
            }
        }
        ModelsCommand::Rollback { category, reason, expected_generation } => {
            let entry = client
                .rollback(&category, &reason, expected_generation)
                .await
                .with_context(|| format!("rolling back {category}"))?;
            if json {
                println!("{}", output::activation_json(&entry));
            } else {
                println!("{}", output::activation_line("rolled back", &entry));
            }
        }
    }
    Ok(())
}

async fn jobs_command(client: &Client, action: JobsCommand, json: bool) -> Result<ExitCode> {
    match action {
        JobsCommand::List { category } => {
            let jobs = client.list_jobs(category.as_deref()).await.context("listing jobs")?;
            if json {
                println!("{}", json!({ "jobs": jobs.iter().map(output::job_json).collect::<Result<Vec<_>, _>>()? }));
            } else {
                output::jobs_table(&jobs).iter().for_each(|l| println!("{l}"));
            }
        }
        JobsCommand::Get { id } => {
            let job = client.get_job(&id).await.with_context(|| format!("getting job {id}"))?;
            if json {
                println!("{}", output::job_json(&job)?);
            } else {
                output::job_lines(&job).iter().for_each(|l| println!("{l}"));
            }
        }
        JobsCommand::Sets { category } => {
            let sets = client.list_regression_sets(&category).await.context("listing regression sets")?;
            if json {
                let sets: Vec<udapose_api::RegressionSet> = sets
                    .into_iter()
                    .map(TryInto::try_into)
                    .collect::<Result<_, String>>()
                    .map_err(anyhow::Error::msg)?;
                println!("{}", json!({ "sets": sets }));
            } else {
                output::regression_sets_table(&sets).iter().for_each(|l| println!("{l}"));
            }
        }
        JobsCommand::Watch { id, after_seq } => return follow::watch(client, &id, after_seq, json).await,
        JobsCommand::Cancel { id, reason } => {
            let job = client.cancel_job(&id, &reason).await.with_context(|| format!("cancelling job {id}"))?;
            if json {
                println!("{}", output::job_json(&job)?);
            } else {
                println!("{}", output::job_final_line(&job));
            }
        }
    }
    Ok(ExitCode::SUCCESS)
}

async fn estimate(
    client: &Client,
    category: &str,
    boxes: &[BoundingBox],
    json: bool,
    inputs: &[PathBuf],
) -> Result<()> {
    let files = expand(inputs)?;
    let width = files.iter().map(|f| f.display().to_string().len() + 3).max().unwrap_or(0).max("IMAGE".len());
    // The header comes with the first row: a run whose images all fail prints no table.
    let mut header = !json;
    let mut failed = 0;
    for file in &files {
        let name = file.display().to_string();
        let result = async {
            let bytes = read_input(file)?;
            let request = EstimateRequest {
                category: category.into(),
                input: Some(Input::Image(bytes)),
                boxes: boxes.to_vec(),
                frame_id: name.clone(),
                options: None,
            };
            client.estimate(request).await.map_err(anyhow::Error::from)
        }
        .await;
        match result {
            Ok(response) if json => println!("{}", response_json(&name, &response)),
            Ok(response) => {
                if std::mem::take(&mut header) {
                    println!(
                        "{:width$}  {:>9}  {:>9}  {:>8}  {:>8}  {:>6}  VERSION",
                        "IMAGE", "AZIMUTH", "ELEVATION", "THETA", "DISTANCE", "SCORE"
                    );
                }
                print_rows(&name, &response, width)
            }
            Err(e) => {
                failed += 1;
                eprintln!("{name}: {e:#}");
            }
        }
    }
    if failed > 0 {
        bail!("{failed} of {} images failed", files.len());
    }
    Ok(())
}

fn print_rows(name: &str, response: &EstimateResponse, width: usize) {
    for (i, p) in response.estimates.iter().enumerate() {
        let label = if response.estimates.len() > 1 { format!("{name}#{i}") } else { name.to_owned() };
        println!(
            "{label:width$}  {:>8.1}°  {:>8.1}°  {:>7.1}°  {:>8.3}  {:>6.3}  {}",
            p.azimuth_deg, p.elevation_deg, p.theta_deg, p.distance, p.score, p.model_version
        );
    }
}

/// The HTTP API's answer (`udapose-api`'s type, converted from gRPC), plus the image's name.
fn response_json(name: &str, r: &EstimateResponse) -> Value {
    #[derive(serde::Serialize)]
    struct Named<'a> {
        image: &'a str,
        #[serde(flatten)]
        answer: udapose_api::EstimateAnswer,
    }
    output::to_value(Named { image: name, answer: r.clone().into() })
}

/// The HTTP `GET /v1/models` answer.
fn models_json(models: &[ModelInfo]) -> Value {
    output::to_value(udapose_api::ModelList { models: models.iter().cloned().map(Into::into).collect() })
}

fn print_table(models: &[ModelInfo]) {
    if models.is_empty() {
        println!("no models configured");
        return;
    }
    let width = models.iter().map(|m| m.category.len()).max().unwrap_or(0).max("CATEGORY".len());
    println!("{:width$}  {:5}  VERSION", "CATEGORY", "READY");
    for m in models {
        let ready = if m.ready { "yes" } else { "no" };
        let version = if m.version.is_empty() { "-" } else { &m.version };
        println!("{:width$}  {ready:5}  {version}", m.category);
    }
}
