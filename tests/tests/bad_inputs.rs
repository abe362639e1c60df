//! Every bad input of the issue, over HTTP and gRPC, answered with its status and a clear
//! message; the server is healthy and serves afterwards. The server runs with a token and a
//! 1 MB request limit. Needs `make test`'s quick model and data.

mod support;

use std::io::Cursor;

use support::{HttpResponse, Server, quick_images};
use tonic::Code;
use udapose_client::{Client, ClientOptions};

const TOKEN: &str = "s3cret-token";
const LIMIT: usize = 1_000_000;

fn png(width: u32, height: u32) -> Vec<u8> {
    let img = image::RgbImage::from_fn(width, height, |x, y| image::Rgb([x as u8, y as u8, 90]));
    let mut out = Vec::new();
    img.write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png).unwrap();
    out
}

/// A valid PNG signature and IHDR chunk claiming 30000×30000 pixels (2.7 GB of RGB), and an
/// IDAT that would inflate to it: a decompression bomb's header.
fn bomb() -> Vec<u8> {
    let mut out = png(1, 1);
    out[16..20].copy_from_slice(&30000u32.to_be_bytes());
    out[20..24].copy_from_slice(&30000u32.to_be_bytes());
    let crc = crc32(&out[12..29]); // the IHDR chunk's type and data
    out[29..33].copy_from_slice(&crc.to_be_bytes());
    out
}

/// CRC-32 (ISO-HDLC), as PNG chunks carry it.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 == 1 { (crc >> 1) ^ 0xEDB8_8320 } else { crc >> 1 };
        }
    }
    !crc
}

fn random_bytes(n: usize) -> Vec<u8> {
    let mut x: u64 = 0x9e3779b97f4a7c15;
    (0..n)
        .map(|_| {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as u8
        })
        .collect()
}

#[test]
fn bad_inputs_get_their_status_and_message_and_the_server_stays_healthy() {
    let server = Server::config("bad-inputs")
        .quick_model()
        .arg("--token")
        .arg(TOKEN)
        .arg("--max-request-bytes")
        .arg(LIMIT.to_string())
        .start();
    let good = quick_images("source", 1).remove(0).bytes;
    let auth = format!("Bearer {TOKEN}");
    let post = |path: &str, body: &[u8]| server.request("POST", path, &[("Authorization", &auth)], body);
    let expect = |r: HttpResponse, status: u16, code: &str, message: &str| {
        assert_eq!(r.status, status, "{}\n{}", r.body, server.log());
        let e = &r.json()["error"];
        assert_eq!(e["code"], code, "{}", r.body);
        let text = e["message"].as_str().unwrap();
        assert!(text.contains(message), "{message:?} not in {text:?}");
    };

    let truncated = &good[..good.len() / 2];
    let jpeg = {
        let img = image::load_from_memory(&good).unwrap().to_rgb8();
        let mut out = Vec::new();
        img.write_to(&mut Cursor::new(&mut out), image::ImageFormat::Jpeg).unwrap();
        out
    };
    let cases: Vec<(&str, Vec<u8>, u16, &str, &str)> = vec![
        ("empty body", Vec::new(), 400, "INVALID_ARGUMENT", "empty image"),
        ("truncated PNG", truncated.to_vec(), 400, "INVALID_ARGUMENT", "cannot decode the PNG"),
        ("truncated JPEG", jpeg[..jpeg.len() * 2 / 3].to_vec(), 400, "INVALID_ARGUMENT", "JPEG image: it is truncated"),
        ("decompression bomb", bomb(), 400, "INVALID_ARGUMENT", "30000x30000"),
        ("random bytes", random_bytes(5000), 400, "INVALID_ARGUMENT", "not a PNG, JPEG or WebP"),
        ("1x1 image", png(1, 1), 400, "INVALID_ARGUMENT", "image is 1x1 px"),
    ];
    for (what, body, status, code, message) in &cases {
        eprintln!("{what}");
        expect(post("/v1/pose/car", body), *status, code, message);
    }
    expect(post("/v1/pose/bus", &good), 404, "NOT_FOUND", "unknown category \"bus\"");
    expect(post("/v1/pose/..%2F..%2Fetc%2Fpasswd", &good), 400, "INVALID_ARGUMENT", "invalid category name");
    expect(post("/v1/pose/Car", &good), 400, "INVALID_ARGUMENT", "invalid category name");
    // Unescaped dots and slashes never reach a handler.
    expect(post("/v1/pose/../../etc/passwd", &good), 404, "NOT_FOUND", "no such route");
    expect(post("/v1/pose/car?bbox=1,2,3", &good), 400, "INVALID_ARGUMENT", "bad bbox");
    expect(post("/v1/pose/car?bbox=-10,0,50,50", &good), 400, "INVALID_ARGUMENT", "leaves the 160x64 image");
    expect(post("/v1/pose/car", &vec![0u8; LIMIT + 1]), 413, "RESOURCE_EXHAUSTED", "over the limit");
    // A huge coordinate is quoted short, not as 301 digits.
    let far = post("/v1/pose/car?bbox=0,0,1e300,100", &good);
    assert!(far.body.len() < 300, "{}", far.body);
    expect(far, 400, "INVALID_ARGUMENT", "1e300");
    // A form whose only part is a text field has no image (its text is not tried as one).
    let form = "--XyZ\r\nContent-Disposition: form-data; name=\"foo\"\r\n\r\nbar\r\n--XyZ--\r\n";
    let multipart = [("Authorization", auth.as_str()), ("Content-Type", "multipart/form-data; boundary=XyZ")];
    expect(
        server.request("POST", "/v1/pose/car", &multipart, form.as_bytes()),
        400,
        "INVALID_ARGUMENT",
        "no image part",
    );
    // A wrong method is a JSON error too.
    expect(
        server.request("GET", "/v1/pose/car", &[("Authorization", &auth)], b""),
        405,
        "UNIMPLEMENTED",
        "GET is not allowed",
    );
    // A 1 ms deadline passes in the queue behind a 16-box request (hundreds of ms of work):
    // the request is refused, not computed.
    let busy = "/v1/pose/car?".to_string() + &["bbox=0,0,160,64"; 16].join("&");
    std::thread::scope(|s| {
        let (post, good, busy) = (&post, &good, &busy);
        let busy = s.spawn(move || post(busy, good));
        std::thread::sleep(std::time::Duration::from_millis(50));
        expect(post("/v1/pose/car?timeout_ms=1", good), 504, "DEADLINE_EXCEEDED", "deadline passed");
        assert_eq!(busy.join().unwrap().status, 200);
    });
    let missing = server.request("POST", "/v1/pose/car", &[], &good);
    assert_eq!(missing.header("www-authenticate"), Some("Bearer realm=\"udapose\""), "401 without a challenge");
    expect(missing, 401, "UNAUTHENTICATED", "missing bearer token");
    // The scheme is case-insensitive (RFC 7235).
    let lower = format!("bearer {TOKEN}");
    let ok = server.request("POST", "/v1/pose/car", &[("Authorization", &lower)], &good);
    assert_eq!(ok.status, 200, "lower-case scheme refused: {}", ok.body);
    let wrong = server.request("POST", "/v1/pose/car", &[("Authorization", "Bearer nope")], &good);
    expect(wrong, 401, "UNAUTHENTICATED", "invalid bearer token");
    expect(server.request("GET", "/v1/models", &[], b""), 401, "UNAUTHENTICATED", "missing bearer token");

    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(grpc_cases(&server, &good, &cases));

    // Still alive, ready and serving; health, metrics and the page need no token.
    assert_eq!(server.get("/healthz").0, 200);
    assert_eq!(server.get("/readyz").0, 200, "{}", server.log());
    assert_eq!(server.get("/").0, 200);
    let (code, metrics) = server.get("/metrics");
    assert_eq!(code, 200);
    for needle in [
        "udapose_errors_total{code=\"INVALID_ARGUMENT\"}",
        "udapose_errors_total{code=\"NOT_FOUND\"}",
        "udapose_errors_total{code=\"RESOURCE_EXHAUSTED\"}",
        "udapose_errors_total{code=\"UNAUTHENTICATED\"}",
        "udapose_errors_total{code=\"DEADLINE_EXCEEDED\"}",
    ] {
        assert!(metrics.contains(needle), "{needle} not in\n{metrics}");
    }
    let ok = post("/v1/pose/car", &good);
    assert_eq!(ok.status, 200, "{}", ok.body);
    assert_eq!(ok.json()["estimates"].as_array().unwrap().len(), 1);
}

async fn grpc_cases(server: &Server, good: &[u8], cases: &[(&str, Vec<u8>, u16, &str, &str)]) {
    let options = |token: Option<&str>| ClientOptions {
        token: token.map(str::to_owned),
        retries: 0,
        ..ClientOptions::new(server.grpc_endpoint())
    };
    let client = Client::connect_with(options(Some(TOKEN))).await.unwrap();
    fn code_of<T>(r: Result<T, udapose_client::Error>) -> (Code, String) {
        match r {
            Ok(_) => panic!("accepted"),
            Err(e) => (e.code().unwrap_or_else(|| panic!("{e}")), e.to_string()),
        }
    }
    for (what, body, _, _, message) in cases {
        let (code, text) = code_of(client.estimate(udapose_client::request("car", body.clone())).await);
        assert_eq!(code, Code::InvalidArgument, "{what}: {text}");
        assert!(text.contains(message), "{what}: {message:?} not in {text:?}");
    }
    let (code, text) = code_of(client.estimate(udapose_client::request("bus", good.to_vec())).await);
    assert_eq!(code, Code::NotFound, "{text}");
    let (code, text) = code_of(client.estimate(udapose_client::request("../../etc", good.to_vec())).await);
    assert_eq!(code, Code::InvalidArgument, "{text}");
    let (code, text) = code_of(client.estimate(udapose_client::request("car", vec![0u8; LIMIT + 1])).await);
    assert_eq!(code, Code::ResourceExhausted, "{text}");
    let (code, text) = code_of(client.describe_model("bus").await);
    assert_eq!(code, Code::NotFound, "{text}");

    let anonymous = Client::connect_with(options(None)).await.unwrap();
    let (code, text) = code_of(anonymous.estimate(udapose_client::request("car", good.to_vec())).await);
    assert_eq!(code, Code::Unauthenticated, "{text}");
    let (code, _) = code_of(anonymous.list_models().await);
    assert_eq!(code, Code::Unauthenticated);
    let wrong = Client::connect_with(options(Some("wrong"))).await.unwrap();
    let (code, text) = code_of(wrong.estimate(udapose_client::request("car", good.to_vec())).await);
    assert!(code == Code::Unauthenticated && text.contains("invalid bearer token"), "{text}");

    let answer = client.estimate(udapose_client::request("car", good.to_vec())).await.unwrap();
    assert_eq!(answer.estimates.len(), 1);
}

/// An 8192×8192 RGBA PNG of zeros: 260 KB that decode to 268 MB (470 MB with the RGB copy).
fn zeros_8192() -> Vec<u8> {
    use image::{ImageEncoder, codecs::png};
    let mut out = Vec::new();
    let encoder = png::PngEncoder::new_with_quality(&mut out, png::CompressionType::Best, png::FilterType::NoFilter);
    encoder.write_image(&vec![0; 8192 * 8192 * 4], 8192, 8192, image::ExtendedColorType::Rgba8).unwrap();
    out
}

#[test]
fn sixteen_parallel_bombs_stay_within_the_decoded_budget() {
    let server = Server::config("bombs").quick_model().start();
    let bomb = zeros_8192();
    assert!(bomb.len() < 1_000_000, "{} bytes", bomb.len());
    let good = quick_images("source", 1).remove(0).bytes;
    assert_eq!(server.request("POST", "/v1/pose/car", &[], &good).status, 200);
    let idle = server.memory_kib("VmRSS");
    // Each waits for its share of the default 1024 MiB budget: 2 at a time.
    let statuses: Vec<u16> = std::thread::scope(|s| {
        let send = || server.request("POST", "/v1/pose/car?timeout_ms=300000", &[], &bomb).status;
        let threads: Vec<_> = (0..16).map(|_| s.spawn(send)).collect();
        threads.into_iter().map(|t| t.join().unwrap()).collect()
    });
    assert!(statuses.iter().all(|&s| s == 200), "{statuses:?}\n{}", server.log());
    let peak = server.memory_kib("VmHWM");
    let above = (peak.saturating_sub(idle)) as f64 / (1 << 20) as f64;
    eprintln!(
        "idle {:.2} GiB, peak {:.2} GiB: {above:.2} GiB above idle",
        idle as f64 / 1048576.0,
        peak as f64 / 1048576.0
    );
    // Unbounded, the 16 would hold 7.3 GiB at once.
    assert!(above <= 1.5, "peak RSS {above:.2} GiB above idle");
    assert_eq!(server.get("/readyz").0, 200);
}
