//! Online adaptation against a real server (issue "Online adaptation"): stream target images,
//! a background 3DUDA job, the label-free gate, the hot swap under load, rollback, and
//! `kill -9` during training and during saving. Needs `make test`'s quick model and data.

mod support;

use std::{
    collections::BTreeSet,
    fs,
    path::PathBuf,
    process::{Command, Stdio},
    thread,
    time::{Duration, Instant},
};

use serde_json::Value;
use support::jobs::*;
use support::{QuickImage, Server, beside_tests, quick_images};

#[test]
fn streamed_images_adapt_activate_and_roll_back_without_a_failed_request() {
    // Fog, with the target check off: to two of the four quick models tried, 0.3 % and 0.9 % of
    // the vertices fire on fog, under the check's 2 % (the no-car test covers the check).
    // A second category ("bus": a copy of the quick model) is served beside car: the job on
    // car must change none of its answers.
    let server = Server::config("adapt-online")
        .quick_model()
        .also_as("bus")
        .args(["--adapt-min-images", "100000", "--max-batch", "1", "--min-target-fired", "0"])
        .start();
    let test_images = quick_images("corrupt/fog", 60);
    let (before, _) = accuracy(&server, &test_images);
    let probe = quick_images("source", 1).remove(0);
    let seed_answer = estimate(&server, &probe);
    let seed = seed_answer["model_version"].as_str().unwrap().to_owned();
    let bus_probes: Vec<QuickImage> = quick_images("corrupt/fog", 8);
    let bus_before: Vec<Value> = bus_probes.iter().map(|i| estimate_as(&server, "bus", i)).collect();

    // 8 clients estimate during the whole upload, job and swap.
    let load = Load::start(&server, 8);
    let folder = adapt_images("corrupt/fog");
    let (ok, stdout, stderr) = udapose(&server, &["adapt", "--category", "car", "--images", folder.to_str().unwrap()]);
    assert!(stdout.contains("uploaded 60 images to car: 60 accepted"), "{stdout}\n{stderr}\n{}", server.log());
    // The job converges, passes the gate and is activated.
    let last = stdout.lines().last().unwrap();
    let words: Vec<&str> = last.split_whitespace().collect();
    let job_id = words[1].to_owned();
    let j = job(&server, &job_id);
    let version = j["version"].as_str().unwrap().to_owned();
    assert!(
        matches!(words[..], ["job", _, "ACTIVATED", "version", v] if v == version),
        "the job was not activated:\n{stdout}\n{stderr}\n{}",
        server.log()
    );
    assert!(ok, "udapose adapt exits 0 on ACTIVATED:\n{stdout}\n{stderr}");

    // The swap reaches the workers; then the load stops.
    let deadline = Instant::now() + Duration::from_secs(30);
    while estimate(&server, &probe)["model_version"] != version.as_str() {
        assert!(Instant::now() < deadline, "{version} never served\n{}", server.log());
        thread::sleep(Duration::from_millis(100));
    }
    thread::sleep(Duration::from_millis(500));
    let seen = load.finish();
    let errors: Vec<_> = seen.iter().filter(|(status, _)| *status != 200).collect();
    assert!(
        errors.is_empty(),
        "{} of {} requests failed: {:?}",
        errors.len(),
        seen.len(),
        &errors[..errors.len().min(5)]
    );
    let served: BTreeSet<&str> = seen.iter().map(|(_, v)| v.as_str()).collect();
    assert!(served.contains(seed.as_str()) && served.contains(version.as_str()), "{served:?}");
    // Bus answers exactly as before the job, from the same version.
    for (image, before) in bus_probes.iter().zip(&bus_before) {
        let after = estimate_as(&server, "bus", image);
        assert_eq!((&after["model_version"], &after["estimates"]), (&before["model_version"], &before["estimates"]));
    }
    // Both categories are listed, each with the memory its workers hold.
    let (ok, listed, stderr) = udapose(&server, &["models"]);
    assert!(ok && listed.contains("bus") && listed.contains("car"), "{listed}{stderr}");
    let (_, metrics) = server.get("/metrics");
    let mut bytes_of_both = 0.0;
    for category in ["bus", "car"] {
        let bytes = support::metric(&metrics, &format!("udapose_model_bytes{{category=\"{category}\"}}"));
        // The quick ResNet-18 alone is ~45 MB of f32 weights.
        assert!(bytes > 1e7, "{category}: {bytes} bytes");
        bytes_of_both += bytes;
    }
    assert!(support::metric(&metrics, "udapose_resident_bytes") > bytes_of_both, "{metrics}");
    let (_, versions) = server.get("/v1/models/car/versions");
    let versions: Value = serde_json::from_str(&versions).unwrap();
    let existing: BTreeSet<&str> =
        versions["versions"].as_array().unwrap().iter().map(|v| v["version"].as_str().unwrap()).collect();
    assert!(served.is_subset(&existing), "served {served:?}, store has {existing:?}");

    // The job's record: converged or out of rounds, with the gate's three criteria, all passed.
    let gate = j["last_event"]["gate"].as_array().unwrap();
    let names: Vec<&str> = gate.iter().map(|c| c["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["flip_consistency", "score_margin", "pose_diversity"]);
    assert!(gate.iter().all(|c| c["passed"] == true), "{gate:?}");
    assert!(j["last_event"]["round"].as_u64().unwrap() >= 1);
    // Its images left the buffer (the CLI saw the terminal event; the removal follows it).
    let buffered = || fs::read_dir(server.store_dir().join("buffers/car")).map_or(0, |d| d.count());
    let deadline = Instant::now() + Duration::from_secs(10);
    while buffered() > 0 {
        assert!(Instant::now() < deadline, "{} files still buffered after the job ended", buffered());
        thread::sleep(Duration::from_millis(100));
    }

    // Accuracy on the fog test split is higher: the served version won its domain. The quick
    // model is retrained every run and differs from machine to machine (CPU kernels); on
    // `combined`, where this test used to adapt, five such models went 30 → 22, 21 → 30, 29 → 27
    // and 29 → 34 of 60, and one was rejected by the gate, so no claim held for all of them. On fog
    // all four that were tried here gained 12 to 29 images net (a from-scratch trunk keys on
    // global image statistics, which the adaptation re-learns).
    let (after, versions_after) = accuracy(&server, &test_images);
    assert_eq!(versions_after, BTreeSet::from([version.clone()]));
    let n = test_images.len();
    let lost = before.iter().zip(&after).filter(|(b, a)| **b && !**a).count() as f64;
    let won = before.iter().zip(&after).filter(|(b, a)| !**b && **a).count() as f64;
    let right = |h: &[bool]| h.iter().filter(|&&x| x).count();
    let summary = format!("{}/{n} right before, {}/{n} after ({won} won, {lost} lost)", right(&before), right(&after));
    assert!(won > lost, "Acc@π/6 on fog did not rise: {summary}");
    eprintln!("fog Acc@π/6: {summary}");

    // Rollback restores the seed exactly (same weights, --max-batch 1: bit-identical).
    let (ok, stdout, stderr) = udapose(&server, &["models", "rollback", "car", "--reason", "test"]);
    assert!(ok && stdout.starts_with(&format!("rolled back car version {seed}")), "{stdout}{stderr}");
    let deadline = Instant::now() + Duration::from_secs(30);
    let answer = loop {
        let a = estimate(&server, &probe);
        if a["model_version"] == seed.as_str() {
            break a;
        }
        assert!(Instant::now() < deadline, "rollback never served");
    };
    assert_eq!(answer["estimates"], seed_answer["estimates"]);
    // The log is the audit trail: seed, the job's (or the manual) activation, the rollback.
    let (_, versions) = server.get("/v1/models/car/versions");
    let log: Value = serde_json::from_str(&versions).unwrap();
    let actors: Vec<&str> =
        log["activations"].as_array().unwrap().iter().map(|a| a["actor"].as_str().unwrap()).collect();
    assert_eq!(actors, ["api", format!("job:{job_id}").as_str(), "seed"]);
    // Rollbacks walk back through the log: the seed had no predecessor, so a second one is
    // refused (it used to toggle back to the adapted version).
    let (ok, stdout, stderr) = udapose(&server, &["models", "rollback", "car", "--reason", "again"]);
    assert!(!ok && stderr.contains("nothing to roll back to"), "{stdout}{stderr}");
    assert_eq!(estimate(&server, &probe)["model_version"], seed.as_str());
    // A stale expected generation is refused.
    let r = server.request(
        "POST",
        "/v1/models/car/activate",
        &[],
        format!(r#"{{"version":"{version}","expected_generation":0}}"#).as_bytes(),
    );
    assert_eq!((r.status, r.json()["error"]["code"].as_str()), (409, Some("ABORTED")), "{}", r.body);
}

#[test]
fn a_job_on_images_of_no_car_is_not_activated() {
    // The target check is what stands between such images and the served model: the gate does
    // not (with the check off, jobs on these images passed it on the shipped model and on each
    // of four quick models: a model adapted to them grows more confident on them). So the test
    // runs the shipped model, whose weights are the same on every machine: 0.0% of its visible
    // vertices fire on these images against the 2.2% measured for it (its manifest's
    // min_target_fired, which the reason must name: the gate's default is 2.0%). Quick models,
    // retrained every run, gave 0.3-2.2% here (and 0.2-1.8% on real fog), too close to any
    // threshold for a test that must hold (reports/target-check.md).
    let server = Server::config("adapt-reject")
        .shipped_model()
        .args(["--adapt-min-images", "100000", "--max-batch", "1"])
        .start();
    let seed = active_version(&server);
    let dir = std::env::temp_dir().join(format!("udapose-not-cars-{}", std::process::id()));
    not_cars(&dir, 60);
    let acks = upload(&server, &dir);
    assert!(acks.iter().all(|a| a["status"] == "ACCEPTED"), "{acks:?}");
    let id = start_job(&server);
    let j = wait_job(&server, &id, "finished", terminal);
    assert_eq!(j["state"], "REJECTED", "{j}\n{}", server.log());
    let reason = j["reason"].as_str().unwrap();
    assert!(reason.contains("do not look like car") && reason.contains("nothing was saved"), "{reason}");
    assert!(reason.contains("at least 2.2% needed"), "the model's own threshold: {reason}");
    assert!(j["last_event"]["fired_ratio"].as_f64().unwrap() < 0.02, "{j}");
    // Nothing written, nothing served but the seed.
    let (_, listed) = server.get("/v1/models/car/versions");
    let versions = serde_json::from_str::<Value>(&listed).unwrap()["versions"].as_array().unwrap().len();
    assert_eq!((j["version"].as_str(), versions), (Some(""), 1), "{j}\n{listed}");
    assert_eq!(active_version(&server), seed);
    let _ = fs::remove_dir_all(&dir);
}

#[test]
fn kill_9_during_training_and_during_saving_loses_nothing() {
    let mut server = server("adapt-crash");
    let seed = active_version(&server);
    let acks = upload(&server, &adapt_images("combined"));
    assert!(acks.iter().all(|a| a["status"] == "ACCEPTED"));
    let buffer = server.store_dir().join("buffers/car");
    let records =
        || fs::read_dir(&buffer).unwrap().filter(|e| e.as_ref().unwrap().path().extension().unwrap() == "json").count();
    assert_eq!(records(), 60);
    let id = start_job(&server);
    // The CLI follows the job through both crashes (what `udapose adapt` does after uploading).
    let watcher = Command::new(beside_tests("udapose"))
        .args(["--endpoint", &server.grpc_addr.to_string(), "jobs", "watch", &id])
        .env_remove("UDAPOSE_TOKEN")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();

    // 1. During training: after the first EM round. The restart stops again, for good, in
    //    the middle of writing the version (failpoint), where it is killed once more.
    wait_job(&server, &id, "training", |j| j["last_event"]["round"].as_u64().unwrap_or(0) >= 1);
    // Down for 5 s: longer than the client's own retries (1.5 s), so the CLI must reconnect.
    server.crash_and_spawn_after(Duration::from_secs(5), &[("UDAPOSE_FAILPOINT", "save-version")]);
    assert_eq!(records(), 60, "the buffer lost images");
    let deadline = Instant::now() + JOB_TIMEOUT;
    while !server.log().contains("failpoint save-version: stopped here") {
        assert!(Instant::now() < deadline, "the job never reached saving\n{}", server.log());
        thread::sleep(Duration::from_millis(200));
    }
    assert_eq!(active_version(&server), seed);

    // 2. During saving: a partial version (its files, not its manifest) is left behind; it is
    //    never listed nor served, and the resumed job replaces it.
    let versions = server.store_dir().join("models/car/versions");
    let partial = || {
        fs::read_dir(&versions)
            .unwrap()
            .filter(|e| {
                let path = e.as_ref().unwrap().path();
                path.is_dir() && !path.join("manifest.json").exists()
            })
            .count()
    };
    assert_eq!(partial(), 1);
    server.crash_and_restart(&[]);
    assert_eq!(active_version(&server), seed, "the restart does not serve the last good version");
    let (_, listed) = server.get("/v1/models/car/versions");
    let listed: Value = serde_json::from_str(&listed).unwrap();
    assert_eq!(listed["versions"].as_array().unwrap().len(), 1, "a partial version is listed: {listed}");
    assert_eq!(records(), 60);

    // 3. The job resumes from its buffered images and finishes.
    let j = wait_job(&server, &id, "finished", terminal);
    assert!(["ACTIVATED", "REJECTED"].contains(&j["state"].as_str().unwrap()), "{j}");
    let states: Vec<String> = {
        let dir = server.store_dir().join("jobs").join(&id).join("events");
        let mut files: Vec<PathBuf> = fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
        files.sort();
        files
            .iter()
            .map(|f| {
                serde_json::from_str::<Value>(&fs::read_to_string(f).unwrap()).unwrap()["state"]
                    .as_str()
                    .unwrap()
                    .to_owned()
            })
            .collect()
    };
    assert_eq!(states.iter().filter(|s| *s == "QUEUED").count(), 3, "{states:?}"); // queued, and once per restart
    assert_eq!(partial(), 0, "the resumed job left a partial version");
    let out = watcher.wait_with_output().unwrap();
    let (stdout, stderr) = (String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    let last = stdout.lines().last().unwrap_or("");
    let ended = format!("job {id} {}", j["state"].as_str().unwrap());
    assert!(last.starts_with(&ended), "the CLI did not follow the job to its end:\n{stdout}{stderr}");
    assert!(stderr.contains("reconnecting"), "{stderr}");
    // A finished job's images leave the buffer (just after its terminal event).
    let deadline = Instant::now() + Duration::from_secs(10);
    while records() > 0 {
        assert!(Instant::now() < deadline, "{} images still buffered after the job ended", records());
        thread::sleep(Duration::from_millis(100));
    }
}

#[test]
fn the_buffer_and_the_roles_refuse_clearly() {
    let dir = support::scratch_dir("adapt-roles-tokens");
    fs::create_dir_all(&dir).unwrap();
    let tokens = dir.join("tokens");
    fs::write(&tokens, "read r-token\nwrite w-token\nadmin a-token\n").unwrap();
    let server = Server::config("adapt-roles")
        .quick_model()
        .arg("--token-file")
        .arg(tokens.display().to_string())
        .arg("--buffer-capacity")
        .arg("2")
        .arg("--adapt-min-images")
        .arg("100000")
        .start();
    let auth = |t: &str| format!("Bearer {t}");
    let (read, write, admin) = (auth("r-token"), auth("w-token"), auth("a-token"));
    let post = |path: &str, token: &str, body: &[u8]| server.request("POST", path, &[("authorization", token)], body);
    let images = quick_images("source", 3);

    // Roles: read may not upload; write may not activate, roll back or cancel.
    let r = post("/v1/adapt/car/images", &read, &images[0].bytes);
    assert_eq!((r.status, r.json()["error"]["code"].as_str()), (403, Some("PERMISSION_DENIED")), "{}", r.body);
    assert_eq!(server.request("GET", "/v1/jobs", &[("authorization", &read)], b"").status, 200);
    for path in ["/v1/models/car/rollback", "/v1/jobs/job-x/cancel"] {
        assert_eq!(post(path, &write, b"{}").status, 403, "{path}");
    }
    assert_eq!(post("/v1/adapt/car/images", "", &images[0].bytes).status, 401);

    // The buffer: accepted once, then a duplicate; junk is rejected with its reason; a full
    // buffer rejects with BUFFER_FULL and a Retry-After.
    let ack = |r: support::HttpResponse| r.json()["results"][0].clone();
    assert_eq!(ack(post("/v1/adapt/car/images", &write, &images[0].bytes))["status"], "ACCEPTED");
    let dup = ack(post("/v1/adapt/car/images", &write, &images[0].bytes));
    assert_eq!((dup["status"].as_str(), dup["buffered"].as_u64()), (Some("DUPLICATE"), Some(1)), "{dup}");
    let junk = ack(post("/v1/adapt/car/images", &write, b"not an image"));
    assert!(junk["status"] == "REJECTED" && junk["reason"].as_str().unwrap().starts_with("INVALID_IMAGE"), "{junk}");
    assert_eq!(ack(post("/v1/adapt/car/images", &write, &images[1].bytes))["status"], "ACCEPTED");
    let r = post("/v1/adapt/car/images", &write, &images[2].bytes);
    assert_eq!(r.header("retry-after"), Some("10"));
    let full = ack(r);
    assert!(full["status"] == "REJECTED" && full["reason"].as_str().unwrap().starts_with("BUFFER_FULL"), "{full}");
    assert_eq!(full["rejection"], "BUFFER_FULL", "{full}");
    assert_eq!(post("/v1/adapt/nope/images", &write, &images[2].bytes).status, 404);

    // Too few images for a job; nothing to roll back to; unknown job and version.
    let r = post("/v1/adapt/car/jobs", &write, b"{}");
    assert_eq!((r.status, r.json()["error"]["code"].as_str()), (400, Some("FAILED_PRECONDITION")), "{}", r.body);
    assert!(r.body.contains("too few buffered car images"), "{}", r.body);
    let r = post("/v1/models/car/rollback", &admin, b"{}");
    assert_eq!((r.status, r.json()["error"]["code"].as_str()), (400, Some("FAILED_PRECONDITION")), "{}", r.body);
    assert_eq!(post("/v1/models/car/activate", &admin, br#"{"version":"nope"}"#).status, 404);
    assert_eq!(post("/v1/jobs/job-x/cancel", &admin, b"").status, 404);
    assert_eq!(post("/v1/models/car/activate", &admin, b"{bad json").status, 400);
    let _ = fs::remove_dir_all(&dir);
}

#[test]
fn a_job_never_activates_over_a_newer_generation_and_can_be_cancelled() {
    let server = server("adapt-supersede");
    let seed = active_version(&server);
    let folder = adapt_images("combined");

    // Someone activates another version (the seed's files under another name, generation 1)
    // while the job trains. (Activating the active version writes nothing: still generation 0.)
    let versions = server.store_dir().join("models/car/versions");
    copy_dir(&versions.join(&seed), &versions.join("operator"));
    upload(&server, &folder);
    let id = start_job(&server);
    wait_job(&server, &id, "training", |j| j["last_event"]["round"].as_u64().unwrap_or(0) >= 1);
    let activate = |version: &str| {
        let body = format!(r#"{{"version":"{version}","reason":"operator"}}"#);
        server.request("POST", "/v1/models/car/activate", &[], body.as_bytes())
    };
    let r = activate(&seed);
    assert_eq!((r.status, r.json()["generation"].as_u64()), (200, Some(0)), "{}", r.body);
    let r = activate("operator");
    assert_eq!((r.status, r.json()["generation"].as_u64()), (200, Some(1)), "{}", r.body);
    let j = wait_job(&server, &id, "finished", terminal);
    // SUPERSEDED if its gate passed, REJECTED if not: never activated over generation 1.
    assert!(["SUPERSEDED", "REJECTED"].contains(&j["state"].as_str().unwrap()), "{j}");
    let (_, described) = server.get("/v1/models/car");
    let described: Value = serde_json::from_str(&described).unwrap();
    assert_eq!((described["version"].as_str(), described["generation"].as_u64()), (Some("operator"), Some(1)));

    // A cancelled job stops, keeps no version active, and releases its images.
    let deadline = Instant::now() + Duration::from_secs(10);
    while fs::read_dir(server.store_dir().join("buffers/car")).map_or(0, |d| d.count()) > 0 {
        assert!(Instant::now() < deadline, "the first job's images stayed buffered");
        thread::sleep(Duration::from_millis(100));
    }
    let acks = upload(&server, &folder);
    assert!(acks.iter().all(|a| a["status"] == "ACCEPTED"), "released images are accepted again");
    let id = start_job(&server);
    wait_job(&server, &id, "training", |j| j["last_event"]["round"].as_u64().unwrap_or(0) >= 1);
    // The answer comes once the job has stopped.
    let r = server.request("POST", &format!("/v1/jobs/{id}/cancel?reason=test"), &[], b"");
    assert_eq!((r.status, r.json()["state"].as_str()), (200, Some("CANCELLED")), "{}", r.body);
    let j = wait_job(&server, &id, "finished", terminal);
    assert_eq!(j["state"], "CANCELLED", "{j}");
    assert_eq!(active_version(&server), "operator");
}

/// How many of `images` the active version gets right at π/6.
fn right(server: &Server, images: &[QuickImage]) -> usize {
    accuracy(server, images).0.iter().filter(|&&h| h).count()
}

#[test]
fn a_job_that_would_erase_an_earlier_gain_is_rejected() {
    // Fog is this test's far domain: to the quick model (6 epochs, retrained every CI run) fewer
    // of its vertices fire than the target check's 2 % (1.2 % on one CI run: REJECTED as "not
    // a car" before any training), so the check is off here; the no-car test covers it.
    // Experts off: this test is about the refusal (experts.rs keeps such a job as an expert).
    // --regression-se 0: any fall of the fog set's flip consistency or mean margin refuses. The
    // fog set is the job's held-out share, 8 images here: at the default 2 paired SE the clear
    // job's fall (fog 37 -> 12 of 60 right; flip 0.50 -> 0.25, SE 0.25; margin 0.073 -> 0.045,
    // SE 0.017) is within noise, and one CI run activated it. The threshold itself is
    // engine/tests/gate.rs's.
    let server =
        server_with("adapt-continual", &["--min-target-fired", "0", "--max-experts", "0", "--regression-se", "0"]);
    let seed = active_version(&server);
    let fog_test = quick_images("corrupt/fog", 60);

    // Step 1: fog. The job wins fog (lab/tests/adapt.rs) and leaves its held-out images as a
    // regression set, listed by the HTTP API and `udapose jobs sets`.
    let fog = job_on(&server, "corrupt/fog");
    assert_eq!(fog["state"], "ACTIVATED", "{fog}\n{}", server.log());
    let (fog_id, fog_version) = (fog["job_id"].as_str().unwrap(), fog["version"].as_str().unwrap());
    let (status, body) = server.get("/v1/adapt/car/regression-sets");
    assert_eq!(status, 200, "{body}");
    let sets: Value = serde_json::from_str(&body).unwrap();
    let set = &sets["sets"][0];
    assert_eq!(sets["sets"].as_array().unwrap().len(), 1, "{sets}");
    assert_eq!(
        (set["set_id"].as_str(), set["kind"].as_str(), set["version"].as_str()),
        (Some(fog_id), Some("JOB"), Some(fog_version))
    );
    assert_eq!(set["images"], fog["images_held_out"].as_u64().unwrap().min(32), "{set}");
    let (ok, stdout, stderr) = udapose(&server, &["jobs", "sets", "car"]);
    assert!(
        ok && stdout.lines().nth(1).is_some_and(|l| l.starts_with(fog_id) && l.contains("JOB")),
        "{stdout}{stderr}"
    );

    // Step 2: clear-weather images. On its own domain the candidate beats the fog model (its
    // BatchNorm statistics return to clear images), and on fog it gives back what step 1 won:
    // the gate measures that on the fog set, label-free, and refuses it.
    let clear = job_on(&server, "source");
    let gate = clear["last_event"]["gate"].as_array().unwrap();
    let guarded: Vec<&Value> =
        gate.iter().filter(|c| c["name"].as_str().unwrap().starts_with(&format!("{fog_id}/"))).collect();
    let names: Vec<&str> = guarded.iter().map(|c| c["name"].as_str().unwrap().split('/').nth(1).unwrap()).collect();
    assert_eq!(names, ["flip_consistency", "score_margin", "pose_diversity"], "{gate:?}");
    let verdict = format!("{guarded:?}");
    assert_eq!(active_version(&server), fog_version);
    let fog_right = right(&server, &fog_test);
    serve_version(&server, clear["version"].as_str().unwrap(), &fog_test[0]);
    let clear_right = right(&server, &fog_test);
    serve_version(&server, &seed, &fog_test[0]);
    let seed_right = right(&server, &fog_test);
    eprintln!(
        "fog test Acc@π/6: seed {seed_right}/60, fog job {fog_right}/60, clear job on top {clear_right}/60; fog set: {verdict}"
    );
    assert!(guarded.iter().any(|c| c["passed"] == false), "the fog set's verdict: {verdict}");
    assert_eq!(clear["state"], "REJECTED", "{clear}");
    let reason = clear["reason"].as_str().unwrap();
    assert!(reason.contains(&format!("regress on regression set {fog_id}")), "{reason}");
    // The labels agree with the verdict: the refused version is worse on fog.
    assert!(clear_right < fog_right, "fog: {fog_right} → {clear_right} of 60");

    // An operator's anchor images: the upload route with ?anchor=true keeps them in their own
    // set (listed first), not in the buffer; a resend is a DUPLICATE; a bad flag is refused.
    let clear_test = quick_images("source", 5);
    for (i, image) in clear_test.iter().chain(&clear_test[..1]).enumerate() {
        let r = server.request("POST", "/v1/adapt/car/images?anchor=true", &[], &image.bytes);
        assert_eq!(r.status, 200, "{}", r.body);
        let status = r.json()["results"][0]["status"].as_str().unwrap().to_owned();
        assert_eq!(status, if i < 5 { "ACCEPTED" } else { "DUPLICATE" }, "{}", r.body);
    }
    let r = server.request("POST", "/v1/adapt/car/images?anchor=yes", &[], &clear_test[0].bytes);
    assert_eq!((r.status, r.json()["error"]["code"].as_str()), (400, Some("INVALID_ARGUMENT")), "{}", r.body);
    let (_, body) = server.get("/v1/adapt/car/regression-sets");
    let sets: Value = serde_json::from_str(&body).unwrap();
    let ids: Vec<&str> = sets["sets"].as_array().unwrap().iter().map(|s| s["set_id"].as_str().unwrap()).collect();
    assert_eq!(ids, ["anchor", fog_id], "{sets}");
    assert_eq!((sets["sets"][0]["kind"].as_str(), sets["sets"][0]["images"].as_u64()), (Some("ANCHOR"), Some(5)));

    // The CLI adds anchors over gRPC (two new images, one already held) and starts no job.
    let folder = std::env::temp_dir().join(format!("anchors-{}", std::process::id()));
    std::fs::create_dir_all(&folder).unwrap();
    for (i, image) in quick_images("source", 7)[4..].iter().enumerate() {
        std::fs::write(folder.join(format!("{i}.png")), &image.bytes).unwrap();
    }
    let jobs = || serde_json::from_str::<Value>(&server.get("/v1/jobs").1).unwrap()["jobs"].as_array().unwrap().len();
    let jobs_before = jobs();
    let (ok, stdout, stderr) =
        udapose(&server, &["adapt", "--anchor", "--category", "car", "--images", folder.to_str().unwrap()]);
    std::fs::remove_dir_all(&folder).unwrap();
    assert!(ok, "{stdout}\n{stderr}");
    assert!(
        stdout.contains("uploaded 3 images to car: 2 accepted, 1 duplicate, 0 rejected (anchor set 7/128)"),
        "{stdout}"
    );
    assert_eq!(jobs(), jobs_before, "an anchor upload started a job");
    let (_, body) = server.get("/v1/adapt/car/regression-sets");
    let sets: Value = serde_json::from_str(&body).unwrap();
    assert_eq!(sets["sets"][0]["images"].as_u64(), Some(7), "{sets}");
}
