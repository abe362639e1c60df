//! Jobs on an in-memory store, in a process that records jobs but does not run them (as a
//! serve replica): the claim on buffered images, idempotent starts, persistence, discovery by
//! another process, and cancellation through the store.

use std::{
    io::Cursor,
    path::{Path, PathBuf},
    sync::Arc,
    time::Duration,
};

use tch::Device;
use udapose_engine::{adapt::AdaptConfig, gate::GateConfig};

use super::*;
use crate::{decode::DecodeLimits, metrics::Metrics, worker::WorkerConfig};

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("udapose-jobs-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn models() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../models")
}

fn recorder(store: &Store, registry: &Arc<Registry>) -> Arc<Jobs> {
    let config = JobsConfig {
        min_images: 1000,
        adapt: AdaptConfig::default(),
        gate: GateConfig::default(),
        regression: Default::default(),
        experts: Default::default(),
        device: Device::Cpu,
        decode: DecodeLimits::default(),
        runs_jobs: false,
        enforce_gate: true,
        poll: Duration::ZERO,
        threads: 1,
        nice: 0,
    };
    Jobs::start(store.clone(), registry.clone(), Buffer::new(store.clone(), 500), config).unwrap()
}

/// `n` distinct 32×32 PNGs.
fn images(n: usize) -> Vec<Vec<u8>> {
    (0..n)
        .map(|i| {
            let img = image::RgbImage::from_fn(32, 32, |x, y| image::Rgb([(x * 8) as u8, (y * 8) as u8, i as u8]));
            let mut out = Cursor::new(Vec::new());
            img.write_to(&mut out, image::ImageFormat::Png).unwrap();
            out.into_inner()
        })
        .collect()
}

fn setup(name: &str) -> (PathBuf, Store, Arc<Registry>) {
    let dir = scratch(name);
    let store = Store::in_memory(&dir).unwrap();
    let workers = WorkerConfig::for_tests();
    let registry = Arc::new(Registry::start(store.clone(), &models(), &workers, Arc::new(Metrics::new())).unwrap());
    (dir, store, registry)
}

#[test]
fn a_job_claims_the_buffered_images_once_and_other_processes_see_it() {
    let (dir, store, registry) = setup("claim");
    let jobs = recorder(&store, &registry);
    for bytes in images(40) {
        let ack = jobs.put_target("car", &bytes, false);
        assert_eq!(ack.status, AckStatus::Accepted, "{}", ack.reason);
    }
    let job = jobs.start_job("car", Overrides::default(), Some("client-1".into())).unwrap();
    assert_eq!(job.state, JobState::Queued);
    assert_eq!(job.images_used + job.images_held_out, 40, "every buffered image is claimed");
    assert!(job.images_held_out >= 4 && job.images_used > job.images_held_out);
    // Idempotent: the same client id, or any start while the category is busy, is that job.
    let again = jobs.start_job("car", Overrides::default(), Some("client-1".into())).unwrap();
    let busy = jobs.start_job("car", Overrides::default(), None).unwrap();
    assert_eq!((again.job_id.as_str(), busy.job_id.as_str()), (job.job_id.as_str(), job.job_id.as_str()));
    // Persisted as a spec and a create-only first event.
    let id = &job.job_id;
    assert!(store.exists(&format!("jobs/{id}/job.json")).unwrap());
    assert!(store.exists(&format!("jobs/{id}/events/00000001.json")).unwrap());
    assert_eq!(jobs.events(id, 0).unwrap().len(), 1);
    // Another process on the same store discovers it, with its images claimed.
    let other = recorder(&store, &registry);
    let seen = other.get(id).unwrap();
    assert_eq!((seen.state, seen.images_used), (JobState::Queued, job.images_used));
    assert_eq!(other.list(Some("car")).len(), 1);
    assert!(other.list(Some("bus")).is_empty());
    // Neither process runs it, so a cancellation is asked through the store.
    jobs.cancel(id, "test").unwrap();
    assert_eq!(store.read(&format!("jobs/{id}/cancel.json")).unwrap().as_deref(), Some(&b"test"[..]));
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn too_few_images_and_unknown_jobs_are_clear_errors() {
    let (dir, store, registry) = setup("few");
    let jobs = recorder(&store, &registry);
    for bytes in images(3) {
        jobs.put_target("car", &bytes, false);
    }
    let few = jobs.start_job("car", Overrides::default(), None).unwrap_err();
    assert!(matches!(few, ApiError::FailedPrecondition(ref m) if m.contains("too few buffered car images")), "{few}");
    assert!(jobs.list(None).is_empty(), "nothing was created");
    let missing = jobs.get("job-0-nope").unwrap_err();
    assert!(matches!(missing, ApiError::NotFound(_)), "{missing}");
    let bad = jobs.put_target("car", b"not an image", false);
    assert_eq!(bad.status, AckStatus::Rejected);
    assert!(bad.reason.starts_with("INVALID_IMAGE"), "{}", bad.reason);
    std::fs::remove_dir_all(dir).unwrap();
}
