//! Online adaptation through a real server, for the tests that run jobs: uploads, jobs and
//! their states, estimates and accuracy, background load, scratch images.

use std::{
    collections::BTreeSet,
    fs,
    path::{Path, PathBuf},
    process::Command,
    sync::{
        Arc, Mutex,
        atomic::{AtomicBool, Ordering},
    },
    thread,
    time::{Duration, Instant},
};

use serde_json::Value;

use super::{QuickImage, Server, beside_tests, env_path, geodesic, quick_images, rotation};

/// A job on the quick model (60 images of 64×160) takes ~20 s on 2 cores; generous for CI.
pub const JOB_TIMEOUT: Duration = Duration::from_secs(240);

pub fn adapt_images(domain: &str) -> PathBuf {
    env_path("UDAPOSE_QUICK_DATA").join(domain).join("adapt/images/car")
}

pub fn server(name: &str) -> Server {
    server_with(name, &[])
}

pub fn server_with(name: &str, args: &[&str]) -> Server {
    // No job starts by itself: each test starts its own.
    let mut config =
        Server::config(name).quick_model().arg("--adapt-min-images").arg("100000").arg("--max-batch").arg("1");
    for a in args {
        config = config.arg(*a);
    }
    config.start()
}

pub fn udapose(server: &Server, args: &[&str]) -> (bool, String, String) {
    let out = Command::new(beside_tests("udapose"))
        .arg("--endpoint")
        .arg(server.grpc_addr.to_string())
        .args(args)
        .env_remove("UDAPOSE_TOKEN")
        .output()
        .expect("the udapose binary (build the workspace first)");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

/// Posts every PNG of `dir` to the buffer, one image per request; returns their acks.
pub fn upload(server: &Server, dir: &Path) -> Vec<Value> {
    let mut files: Vec<PathBuf> = fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    files.sort();
    files
        .iter()
        .map(|f| {
            let r = server.request("POST", "/v1/adapt/car/images", &[], &fs::read(f).unwrap());
            assert_eq!(r.status, 200, "{}", r.body);
            r.json()["results"][0].clone()
        })
        .collect()
}

pub fn start_job(server: &Server) -> String {
    let r = server.request("POST", "/v1/adapt/car/jobs", &[], b"{}");
    assert_eq!(r.status, 200, "{}", r.body);
    r.json()["job_id"].as_str().unwrap().to_owned()
}

pub fn job(server: &Server, id: &str) -> Value {
    let (status, body) = server.get(&format!("/v1/jobs/{id}"));
    assert_eq!(status, 200, "{body}");
    serde_json::from_str(&body).unwrap()
}

/// Polls the job until `done` says so.
pub fn wait_job(server: &Server, id: &str, what: &str, done: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + JOB_TIMEOUT;
    loop {
        let j = job(server, id);
        if done(&j) {
            return j;
        }
        assert!(Instant::now() < deadline, "job {id}: not {what} after {JOB_TIMEOUT:?}: {j}\n{}", server.log());
        thread::sleep(Duration::from_millis(200));
    }
}

pub fn terminal(j: &Value) -> bool {
    ["ACTIVATED", "REJECTED", "SUPERSEDED", "FAILED", "CANCELLED"].contains(&j["state"].as_str().unwrap())
}

pub fn active_version(server: &Server) -> String {
    let (_, body) = server.get("/v1/models/car");
    serde_json::from_str::<Value>(&body).unwrap()["version"].as_str().unwrap().to_owned()
}

pub fn estimate(server: &Server, image: &QuickImage) -> Value {
    estimate_as(server, "car", image)
}

pub fn estimate_as(server: &Server, category: &str, image: &QuickImage) -> Value {
    let r = server.request("POST", &format!("/v1/pose/{category}"), &[], &image.bytes);
    assert_eq!(r.status, 200, "{}", r.body);
    r.json()
}

/// Per image, whether the estimate is within π/6 of the truth; and the versions that answered.
pub fn accuracy(server: &Server, images: &[QuickImage]) -> (Vec<bool>, BTreeSet<String>) {
    let mut versions = BTreeSet::new();
    let hits = images
        .iter()
        .map(|image| {
            let a = estimate(server, image);
            versions.insert(a["model_version"].as_str().unwrap().to_owned());
            let p = &a["estimates"][0];
            let angles = ["azimuth", "elevation", "theta"].map(|k| p[k].as_f64().unwrap());
            geodesic(rotation(angles), rotation(image.truth)) < std::f64::consts::PI / 6.0
        })
        .collect();
    (hits, versions)
}

/// Estimates from `clients` threads until stopped; records every status and version.
pub struct Load {
    stop: Arc<AtomicBool>,
    seen: Arc<Mutex<Vec<(u16, String)>>>,
    threads: Vec<thread::JoinHandle<()>>,
}

impl Load {
    pub fn start(server: &Server, clients: usize) -> Load {
        let images = Arc::new(quick_images("source", 4));
        let (stop, seen) = (Arc::new(AtomicBool::new(false)), Arc::new(Mutex::new(Vec::new())));
        let threads = (0..clients)
            .map(|i| {
                let (stop, seen, images, addr) = (stop.clone(), seen.clone(), images.clone(), server.http_addr);
                thread::spawn(move || {
                    let mut k = i;
                    while !stop.load(Ordering::Relaxed) {
                        let image = &images[k % images.len()];
                        k += 1;
                        let seen_now = match super::http_request(addr, "POST", "/v1/pose/car", &[], &image.bytes) {
                            Ok(r) => {
                                let version = serde_json::from_str::<Value>(&r.body)
                                    .ok()
                                    .and_then(|v| v["model_version"].as_str().map(str::to_owned))
                                    .unwrap_or_else(|| r.body.clone());
                                (r.status, version)
                            }
                            Err(e) => (0, e.to_string()), // a transport error counts as a failure
                        };
                        seen.lock().unwrap().push(seen_now);
                    }
                })
            })
            .collect();
        Load { stop, seen, threads }
    }

    pub fn finish(self) -> Vec<(u16, String)> {
        self.stop.store(true, Ordering::Relaxed);
        for t in self.threads {
            t.join().unwrap();
        }
        Arc::try_unwrap(self.seen).unwrap().into_inner().unwrap()
    }
}

pub fn copy_dir(from: &Path, to: &Path) {
    fs::create_dir_all(to).unwrap();
    for entry in fs::read_dir(from).unwrap() {
        let path = entry.unwrap().path();
        fs::copy(&path, to.join(path.file_name().unwrap())).unwrap();
    }
}

/// Images of no car at all: smooth random colour fields and stripes, 160×64: the fields of
/// `udapose_lab::not_objects::colour_field`, which `udapose-lab target-check` measures each
/// model's threshold on (drawn here again: this crate links no libtorch).
pub fn not_cars(dir: &Path, n: usize) {
    fs::create_dir_all(dir).unwrap();
    let mut state = 0x9e37_79b9_7f4a_7c15_u64;
    let mut next = move || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    for i in 0..n {
        let (fx, fy, phase) = (next() * 0.3, next() * 0.3, next() * 6.0);
        let base = [next(), next(), next()];
        let img = image::RgbImage::from_fn(160, 64, |x, y| {
            let wave = ((x as f64 * fx + y as f64 * fy + phase).sin() + 1.0) / 2.0;
            image::Rgb(base.map(|b| ((b * 0.6 + wave * 0.4) * 255.0) as u8))
        });
        img.save(dir.join(format!("{i:03}.png"))).unwrap();
    }
}

/// Activates `version` and waits until it answers.
pub fn serve_version(server: &Server, version: &str, probe: &QuickImage) {
    let body = format!(r#"{{"version":"{version}","reason":"test"}}"#);
    let r = server.request("POST", "/v1/models/car/activate", &[], body.as_bytes());
    assert_eq!(r.status, 200, "{}", r.body);
    let deadline = Instant::now() + Duration::from_secs(30);
    while estimate(server, probe)["model_version"] != version {
        assert!(Instant::now() < deadline, "{version} never served\n{}", server.log());
        thread::sleep(Duration::from_millis(100));
    }
}

/// Uploads one domain's adapt images, runs a job on them to its end; the job.
pub fn job_on(server: &Server, domain: &str) -> Value {
    let acks = upload(server, &adapt_images(domain));
    assert!(acks.iter().all(|a| a["status"] == "ACCEPTED"), "{acks:?}");
    let id = start_job(server);
    wait_job(server, &id, "finished", terminal)
}
