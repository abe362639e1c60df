//! `udapose-bench bad-inputs`: every bad input of the hostile-user review (issue 21), over HTTP
//! and gRPC, against a real `udapose-server` with a token and a 1 MB request limit. Records per
//! input the status expected and received, the message, panics in the server's log and whether
//! the server was healthy after it; writes `reports/bad-inputs.md`. Exits non-zero when a row
//! is not as specified, so the table is also a check.

use std::{
    io::Cursor,
    path::{Path, PathBuf},
};

use anyhow::{Context, Result, ensure};
use udapose_client::{Client, ClientOptions};
use udapose_lab::atomic::write_atomic;

use crate::harness::{ServerProcess, command_line, git_commit, machine, read_images, request, server_binary};

const TOKEN: &str = "bench-token";
const LIMIT: usize = 1_000_000;

#[derive(clap::Args)]
pub struct BadInputsArgs {
    /// Model directory (served as category `car`).
    #[arg(long, default_value = "models/car")]
    model: PathBuf,
    /// Folder of PNG crops; the first is the good image the bad ones are made from.
    #[arg(long, default_value = "data/syncar-ood-standard/source/test/images/car")]
    images: PathBuf,
    /// The server binary (default: next to this one).
    #[arg(long)]
    server: Option<PathBuf>,
    #[arg(long, default_value = "reports/bad-inputs.md")]
    out: PathBuf,
}

/// One row of the table.
struct Row {
    input: String,
    transport: &'static str,
    expected: String,
    got: String,
    message: String,
    panics: usize,
    healthy: bool,
}

impl Row {
    fn ok(&self) -> bool {
        self.expected == self.got && self.panics == 0 && self.healthy
    }
}

pub fn run(args: &BadInputsArgs) -> Result<()> {
    let good = read_images(&args.images, 1)?.remove(0);
    let binary = server_binary(args.server.as_deref())?;
    let model = std::fs::canonicalize(&args.model).with_context(|| format!("model {}", args.model.display()))?;
    let (server, grpc) = start(&binary, &model)?;
    let mut rows = Vec::new();
    let auth = format!("Bearer {TOKEN}");
    for (input, path, headers, body, expected) in http_cases(&good, &auth)? {
        let (status, answer) = request(server.http, method(&path), strip(&path), &headers_of(&headers), &body)?;
        let message = serde_json::from_str::<serde_json::Value>(&answer)
            .ok()
            .and_then(|v| v["error"]["message"].as_str().map(str::to_owned))
            .unwrap_or_default();
        rows.push(row(&server, input, "HTTP", expected.to_string(), status.to_string(), message));
    }
    let runtime = tokio::runtime::Runtime::new()?;
    for (input, category, token, body, expected) in grpc_cases(&good)? {
        let options =
            ClientOptions { token: token.map(str::to_owned), retries: 0, ..ClientOptions::new(grpc.to_string()) };
        let outcome = runtime.block_on(async {
            let client = Client::connect_with(options).await?;
            client.estimate(udapose_client::request(category, body)).await
        });
        let (got, message) = match outcome {
            Ok(_) => ("OK".to_string(), String::new()),
            Err(e) => (e.code().map_or_else(|| "no status".into(), |c| format!("{c:?}")), e.to_string()),
        };
        rows.push(row(&server, input, "gRPC", expected.to_string(), got, message));
    }
    let md = markdown(args, &rows);
    write_atomic(&args.out, md.as_bytes())?;
    eprintln!("wrote {}", args.out.display());
    let bad: Vec<&Row> = rows.iter().filter(|r| !r.ok()).collect();
    ensure!(
        bad.is_empty(),
        "{} rows not as specified: {}",
        bad.len(),
        bad.iter().map(|r| r.input.as_str()).collect::<Vec<_>>().join(", ")
    );
    Ok(())
}

/// A server with a token and the 1 MB limit, the shipped model as `car`.
fn start(binary: &Path, model: &Path) -> Result<(ServerProcess, std::net::SocketAddr)> {
    let limit = LIMIT.to_string();
    ServerProcess::serve_model(binary, model, "bad-inputs", &["--token", TOKEN, "--max-request-bytes", &limit], false)
}

/// The row for the answer just received: panics logged so far, and a health check.
fn row(
    server: &ServerProcess,
    input: &str,
    transport: &'static str,
    expected: String,
    got: String,
    message: String,
) -> Row {
    let panics = server.log().matches("panicked").count();
    let healthy = request(server.http, "GET", "/readyz", &[], b"").is_ok_and(|(s, _)| s == 200);
    let message = message.chars().take(140).collect::<String>().replace('|', "\\|");
    Row { input: input.to_string(), transport, expected, got, message, panics, healthy }
}

type HttpCase = (&'static str, String, Vec<(String, String)>, Vec<u8>, u16);

fn http_cases(good: &[u8], auth: &str) -> Result<Vec<HttpCase>> {
    let h = |pairs: &[(&str, &str)]| pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect::<Vec<_>>();
    let a = h(&[("Authorization", auth)]);
    let post = |p: &str| format!("POST {p}");
    let form = "--XyZ\r\nContent-Disposition: form-data; name=\"foo\"\r\n\r\nbar\r\n--XyZ--\r\n";
    let jpeg = jpeg(good)?;
    Ok(vec![
        ("empty body", post("/v1/pose/car"), a.clone(), Vec::new(), 400),
        ("truncated PNG", post("/v1/pose/car"), a.clone(), good[..good.len() / 2].to_vec(), 400),
        ("truncated JPEG", post("/v1/pose/car"), a.clone(), jpeg[..jpeg.len() * 2 / 3].to_vec(), 400),
        ("PNG header claiming 30000×30000", post("/v1/pose/car"), a.clone(), bomb_header(), 400),
        ("8192×8192 PNG of zeros (valid)", post("/v1/pose/car?timeout_ms=120000"), a.clone(), zeros_8192()?, 200),
        ("random bytes", post("/v1/pose/car"), a.clone(), noise(5000), 400),
        ("1×1 image", post("/v1/pose/car"), a.clone(), png(1, 1)?, 400),
        ("unknown category", post("/v1/pose/bus"), a.clone(), good.to_vec(), 404),
        ("escaped path traversal", post("/v1/pose/..%2F..%2Fetc%2Fpasswd"), a.clone(), good.to_vec(), 400),
        ("upper-case category", post("/v1/pose/Car"), a.clone(), good.to_vec(), 400),
        ("bbox with 3 numbers", post("/v1/pose/car?bbox=1,2,3"), a.clone(), good.to_vec(), 400),
        ("bbox outside the image", post("/v1/pose/car?bbox=-10,0,50,50"), a.clone(), good.to_vec(), 400),
        ("bbox 0,0,1e300,100", post("/v1/pose/car?bbox=0,0,1e300,100"), a.clone(), good.to_vec(), 400),
        ("body over the limit", post("/v1/pose/car"), a.clone(), vec![0; LIMIT + 1], 413),
        ("timeout_ms=1", post("/v1/pose/car?timeout_ms=1"), a.clone(), good.to_vec(), 504),
        ("no token", post("/v1/pose/car"), Vec::new(), good.to_vec(), 401),
        ("wrong token", post("/v1/pose/car"), h(&[("Authorization", "Bearer nope")]), good.to_vec(), 401),
        (
            "lower-case `bearer` scheme",
            post("/v1/pose/car"),
            h(&[("Authorization", &format!("bearer {TOKEN}"))]),
            good.to_vec(),
            200,
        ),
        ("GET on the estimate route", "GET /v1/pose/car".into(), a.clone(), Vec::new(), 405),
        (
            "multipart form without a file",
            post("/v1/pose/car"),
            [a.clone(), h(&[("Content-Type", "multipart/form-data; boundary=XyZ")])].concat(),
            form.as_bytes().to_vec(),
            400,
        ),
        ("the good image", post("/v1/pose/car"), a, good.to_vec(), 200),
    ])
}

type GrpcCase = (&'static str, &'static str, Option<&'static str>, Vec<u8>, &'static str);

fn grpc_cases(good: &[u8]) -> Result<Vec<GrpcCase>> {
    let t = Some(TOKEN);
    let jpeg = jpeg(good)?;
    Ok(vec![
        ("empty image", "car", t, Vec::new(), "InvalidArgument"),
        ("truncated PNG", "car", t, good[..good.len() / 2].to_vec(), "InvalidArgument"),
        ("truncated JPEG", "car", t, jpeg[..jpeg.len() * 2 / 3].to_vec(), "InvalidArgument"),
        ("PNG header claiming 30000×30000", "car", t, bomb_header(), "InvalidArgument"),
        ("random bytes", "car", t, noise(5000), "InvalidArgument"),
        ("unknown category", "bus", t, good.to_vec(), "NotFound"),
        ("path traversal category", "../../etc", t, good.to_vec(), "InvalidArgument"),
        ("message over the limit", "car", t, vec![0; LIMIT + 1], "ResourceExhausted"),
        ("no token", "car", None, good.to_vec(), "Unauthenticated"),
        ("wrong token", "car", Some("nope"), good.to_vec(), "Unauthenticated"),
        ("the good image", "car", t, good.to_vec(), "OK"),
    ])
}

fn method(line: &str) -> &str {
    line.split_once(' ').map_or("POST", |(m, _)| m)
}

fn strip(line: &str) -> &str {
    line.split_once(' ').map_or(line, |(_, p)| p)
}

fn headers_of(pairs: &[(String, String)]) -> Vec<(&str, &str)> {
    pairs.iter().map(|(k, v)| (k.as_str(), v.as_str())).collect()
}

fn png(width: u32, height: u32) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    image::RgbImage::new(width, height).write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)?;
    Ok(out)
}

fn jpeg(png: &[u8]) -> Result<Vec<u8>> {
    let mut out = Vec::new();
    image::load_from_memory(png)?.to_rgb8().write_to(&mut Cursor::new(&mut out), image::ImageFormat::Jpeg)?;
    Ok(out)
}

/// 260 KB that decode to 268 MB.
fn zeros_8192() -> Result<Vec<u8>> {
    use image::{ImageEncoder, codecs::png};
    let mut out = Vec::new();
    let encoder = png::PngEncoder::new_with_quality(&mut out, png::CompressionType::Best, png::FilterType::NoFilter);
    encoder.write_image(&vec![0; 8192 * 8192 * 4], 8192, 8192, image::ExtendedColorType::Rgba8)?;
    Ok(out)
}

/// A 1×1 PNG whose IHDR (CRC fixed) claims 30000×30000.
fn bomb_header() -> Vec<u8> {
    let mut out = png(1, 1).expect("a 1×1 PNG encodes");
    out[16..20].copy_from_slice(&30000u32.to_be_bytes());
    out[20..24].copy_from_slice(&30000u32.to_be_bytes());
    let mut crc = !0u32;
    for &b in &out[12..29] {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    out[29..33].copy_from_slice(&(!crc).to_be_bytes());
    out
}

fn noise(n: usize) -> Vec<u8> {
    let mut x: u64 = 0x9e37_79b9_7f4a_7c15;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect()
}

fn markdown(args: &BadInputsArgs, rows: &[Row]) -> String {
    let command = command_line();
    let ok = rows.iter().filter(|r| r.ok()).count();
    let mut md = format!(
        "# Bad inputs\n\nEvery bad input of the hostile-user review (issue 21) sent to `udapose-server` on `{}` \
         (a token, `--max-request-bytes {LIMIT}`), over HTTP and gRPC. *Panics*: `panicked` lines in the \
         server's log so far; *healthy*: `/readyz` answered 200 right after.\n\n\
         Produced by `{command}` at commit {}, on {}.\n\n**{ok} of {} rows as specified.**\n\n\
         | input | transport | expected | got | message | panics | healthy after |\n|---|---|---|---|---|---|---|\n",
        args.model.display(),
        git_commit(),
        machine(),
        rows.len()
    );
    for r in rows {
        let mark = if r.ok() { "" } else { " **✗**" };
        md += &format!(
            "| {} | {} | {} | {}{mark} | {} | {} | {} |\n",
            r.input,
            r.transport,
            r.expected,
            r.got,
            r.message,
            r.panics,
            if r.healthy { "yes" } else { "**no**" }
        );
    }
    md += "\nA gRPC message over the limit is refused by tonic before any handler runs: its status \
           carries the code and tonic's message but no ErrorInfo detail (clients should switch on the \
           code). The 8192×8192 image decodes within the in-flight budget (`--max-decoded-mib`); \
           `tests/tests/bad_inputs.rs` checks the server's peak memory under 16 of them at once.\n";
    md
}
