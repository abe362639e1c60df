//! Regression sets (ARCHITECTURE.md "Validation gate"): per category, the images of domains the
//! service has already adapted to, on which the gate forbids a candidate to get worse. Without
//! labels and without the source data: each activated job leaves its held-out images here, and
//! an operator may upload anchor images (conditions that must never get worse).
//!
//! ```text
//! regression/<category>/<job-id>/<sha256>.img   a job's held-out images (create-only)
//! regression/<category>/<job-id>/set.json       written last: the set counts once this exists
//! regression/<category>/anchor/<sha256>.img     anchor images, each complete on its own
//! ```
//!
//! A job's set is written before its version is activated, so a crash in between leaves it
//! complete and a rerun finds it; a set counts only once its version appears in the activation
//! log (a superseded job's set never does). Bounded: at most `per_job` images a job, `max_images`
//! over the job sets (the oldest sets are thinned first, to the gate's minimum, then dropped) and
//! `max_anchor` anchor images.

use std::collections::BTreeSet;

use serde::{Deserialize, Serialize};
pub use udapose_api::{RegressionSet, SetKind};

use crate::buffer::{AckStatus, sha256_hex};
use crate::store::{Store, StoreError, nanos};

/// The anchor set's id (job ids start with `job-`).
pub const ANCHOR: &str = "anchor";

#[derive(Clone, Debug)]
pub struct RegressionConfig {
    /// Whether jobs leave regression sets and the gate guards them (`--no-regression-sets`
    /// turns both off: each job judged on its own held-out images alone, for comparisons).
    pub enabled: bool,
    /// Held-out images a job leaves (the first by sha256: a fixed, unbiased sample).
    pub per_job: usize,
    /// Images over every job set of a category.
    pub max_images: usize,
    /// Anchor images of a category.
    pub max_anchor: usize,
    /// A thinned set keeps at least this many images (the gate's `min_images`).
    pub min_images: usize,
}

impl Default for RegressionConfig {
    fn default() -> Self {
        RegressionConfig { enabled: true, per_job: 32, max_images: 256, max_anchor: 128, min_images: 4 }
    }
}

/// A job set's record: its images are listed so a thinned set is told apart from a torn one.
#[derive(Clone, Debug, Serialize, Deserialize)]
struct SetRecord {
    job_id: String,
    version: String,
    created: f64,
    images: Vec<String>,
}

/// A set's images, as the gate reads them.
pub struct SetImages {
    pub set: RegressionSet,
    pub shas: Vec<String>,
}

#[derive(Clone)]
pub struct Regression {
    store: Store,
    pub config: RegressionConfig,
}

fn prefix(category: &str, set: &str) -> String {
    format!("regression/{category}/{set}")
}

fn image_key(category: &str, set: &str, sha: &str) -> String {
    format!("{}/{sha}.img", prefix(category, set))
}

fn shas_in(files: &[String]) -> BTreeSet<String> {
    files
        .iter()
        .filter_map(|f| f.strip_suffix(".img"))
        .filter(|s| s.len() == 64 && s.bytes().all(|b| b.is_ascii_hexdigit()))
        .map(str::to_owned)
        .collect()
}

impl Regression {
    pub fn new(store: Store, config: RegressionConfig) -> Self {
        Regression { store, config }
    }

    /// The sets the gate guards, oldest first (the anchor set, when it has images, first):
    /// job sets whose version was activated, with the images still present.
    pub fn sets(&self, category: &str) -> Result<Vec<SetImages>, StoreError> {
        let activated: BTreeSet<String> =
            self.store.activations(category)?.into_iter().filter_map(|(_, a)| a.job_id).collect();
        let mut out = Vec::new();
        let anchor = shas_in(&self.store.list(&prefix(category, ANCHOR))?.files);
        if !anchor.is_empty() {
            let set = RegressionSet {
                set_id: ANCHOR.into(),
                kind: SetKind::Anchor,
                version: String::new(),
                created: 0.0,
                images: anchor.len() as u32,
            };
            out.push(SetImages { set, shas: anchor.into_iter().collect() });
        }
        let mut jobs = Vec::new();
        for dir in self.store.list(&format!("regression/{category}"))?.dirs {
            if dir == ANCHOR || !activated.contains(&dir) {
                continue;
            }
            let Some(record) = self.store.read_json::<SetRecord>(&format!("{}/set.json", prefix(category, &dir)))?
            else {
                continue; // torn: its job reruns and completes it
            };
            let present = shas_in(&self.store.list(&prefix(category, &dir))?.files);
            let shas: Vec<String> = record.images.iter().filter(|s| present.contains(*s)).cloned().collect();
            if shas.is_empty() {
                continue;
            }
            let set = RegressionSet {
                set_id: record.job_id.clone(),
                kind: SetKind::Job,
                version: record.version.clone(),
                created: record.created,
                images: shas.len() as u32,
            };
            jobs.push(SetImages { set, shas });
        }
        jobs.sort_by(|a, b| a.set.created.total_cmp(&b.set.created).then(a.set.set_id.cmp(&b.set.set_id)));
        out.extend(jobs);
        Ok(out)
    }

    pub fn read(&self, category: &str, set_id: &str, sha: &str) -> Result<Vec<u8>, StoreError> {
        let key = image_key(category, set_id, sha);
        self.store.read(&key)?.ok_or_else(|| StoreError::Corrupt { path: key, reason: "missing".into() })
    }

    /// The held-out images a job leaves, from `held_out` (sorted by sha256): the first `per_job`.
    pub fn sample<'a>(&self, held_out: &'a [String]) -> Vec<&'a String> {
        let mut shas: Vec<&String> = held_out.iter().collect();
        shas.sort();
        shas.truncate(self.config.per_job);
        shas
    }

    /// Writes job `job_id`'s set (before its version is activated; a rerun completes or keeps
    /// it), then thins the category's job sets to `max_images`. `image(sha)` gives the bytes.
    pub fn record(
        &self,
        category: &str,
        job_id: &str,
        version: &str,
        shas: &[&String],
        image: impl Fn(&str) -> Result<Vec<u8>, StoreError>,
    ) -> Result<(), StoreError> {
        let record_key = format!("{}/set.json", prefix(category, job_id));
        if self.store.exists(&record_key)? {
            return Ok(());
        }
        for sha in shas {
            self.store.create(&image_key(category, job_id, sha), image(sha)?)?;
        }
        let record = SetRecord {
            job_id: job_id.into(),
            version: version.into(),
            created: nanos() as f64 / 1e9,
            images: shas.iter().map(|s| s.to_string()).collect(),
        };
        self.store.create(&record_key, serde_json::to_vec_pretty(&record).expect("a set record serialises"))?;
        Ok(())
    }

    /// Keeps the category's job sets within `max_images`: the oldest sets lose images first (to
    /// `min_images` each, in sha256 order), then the oldest sets go. `keep` (the set just
    /// recorded) is never thinned.
    pub fn thin(&self, category: &str, keep: &str) -> Result<(), StoreError> {
        let sets: Vec<SetImages> = self.sets(category)?.into_iter().filter(|s| s.set.kind == SetKind::Job).collect();
        // `keep` is thinned for before its job is activated, when sets() does not list it yet.
        let unlisted = if sets.iter().any(|s| s.set.set_id == keep) { 0 } else { self.recorded(category, keep)? };
        let mut total: usize = sets.iter().map(|s| s.shas.len()).sum::<usize>() + unlisted;
        let remove = |set: &SetImages, shas: &[String]| -> Result<(), StoreError> {
            for sha in shas {
                self.store.delete(&image_key(category, &set.set.set_id, sha))?;
            }
            Ok(())
        };
        let floor = self.config.min_images;
        for set in sets.iter().filter(|s| s.set.set_id != keep) {
            if total <= self.config.max_images {
                return Ok(());
            }
            let cut = (total - self.config.max_images).min(set.shas.len().saturating_sub(floor));
            remove(set, &set.shas[..cut])?;
            total -= cut;
        }
        for set in sets.iter().filter(|s| s.set.set_id != keep) {
            if total <= self.config.max_images {
                break;
            }
            let left = set.shas.len().min(floor);
            remove(set, &set.shas[set.shas.len() - left..])?;
            total -= left;
        }
        Ok(())
    }

    /// The images of a recorded job set, activated or not (0 when there is none).
    fn recorded(&self, category: &str, set_id: &str) -> Result<usize, StoreError> {
        let key = format!("{}/set.json", prefix(category, set_id));
        Ok(self.store.read_json::<SetRecord>(&key)?.map_or(0, |r| r.images.len()))
    }

    /// Keeps an anchor image (already decoded and checked by the caller) unless the anchor set
    /// is full. Returns the status and the anchor set's size afterwards.
    pub fn put_anchor(&self, category: &str, bytes: &[u8]) -> Result<(AckStatus, usize), StoreError> {
        let sha = sha256_hex(bytes);
        let present = shas_in(&self.store.list(&prefix(category, ANCHOR))?.files);
        if present.contains(&sha) {
            return Ok((AckStatus::Duplicate, present.len()));
        }
        if present.len() >= self.config.max_anchor {
            return Ok((AckStatus::Rejected, present.len()));
        }
        let created = self.store.create(&image_key(category, ANCHOR, &sha), bytes.to_vec())?;
        let status = if created { AckStatus::Accepted } else { AckStatus::Duplicate };
        Ok((status, present.len() + usize::from(created)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::store::Activation;

    fn sha(i: usize) -> String {
        sha256_hex(format!("image {i}").as_bytes())
    }

    /// An activation-log entry naming `job_id` (what makes its set count).
    fn activated(store: &Store, generation: u64, job_id: &str) {
        let entry = Activation {
            version: format!("v-{job_id}"),
            previous: None,
            actor: format!("job:{job_id}"),
            reason: String::new(),
            time: 0,
            job_id: Some(job_id.into()),
        };
        let key = format!("models/car/activations/{generation:020}.json");
        assert!(store.create(&key, serde_json::to_vec(&entry).unwrap()).unwrap());
    }

    fn record(r: &Regression, job_id: &str, images: std::ops::Range<usize>) {
        let shas: Vec<String> = images.clone().map(sha).collect();
        let chosen = r.sample(&shas);
        let bytes = |s: &str| Ok(format!("bytes of {s}").into_bytes());
        r.record("car", job_id, &format!("v-{job_id}"), &chosen, bytes).unwrap();
        r.thin("car", job_id).unwrap();
    }

    fn sizes(r: &Regression) -> Vec<(String, usize)> {
        r.sets("car").unwrap().into_iter().map(|s| (s.set.set_id, s.shas.len())).collect()
    }

    #[test]
    fn sets_count_once_activated_are_bounded_and_thinned_oldest_first() {
        let root = std::env::temp_dir().join(format!("udapose-regression-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let store = Store::open(&root).unwrap();
        let config = RegressionConfig { enabled: true, per_job: 10, max_images: 24, max_anchor: 2, min_images: 4 };
        let r = Regression::new(store.clone(), config);

        // A set is written before its activation: until the log names its job it does not count
        // (a superseded job's never does), and recording again keeps what is there.
        record(&r, "job-a", 0..30);
        assert!(sizes(&r).is_empty());
        activated(&store, 1, "job-a");
        assert_eq!(sizes(&r), [("job-a".into(), 10)]);
        let set = &r.sets("car").unwrap()[0];
        assert_eq!((set.set.kind, set.set.version.as_str()), (SetKind::Job, "v-job-a"));
        let mut first_ten: Vec<String> = (0..30).map(sha).collect();
        first_ten.sort();
        first_ten.truncate(10);
        assert_eq!(set.shas, first_ten, "the first per_job images by sha256");
        assert_eq!(r.read("car", "job-a", &set.shas[0]).unwrap(), format!("bytes of {}", set.shas[0]).into_bytes());
        record(&r, "job-a", 30..60);
        assert_eq!(r.sets("car").unwrap()[0].shas, first_ten);

        // A torn set (images, no set.json) is not a set.
        store.create(&format!("regression/car/job-torn/{}.img", sha(99)), b"x".to_vec()).unwrap();
        activated(&store, 2, "job-torn");
        assert_eq!(sizes(&r).len(), 1);

        // Over max_images (24) the oldest sets are thinned to min_images, then dropped.
        activated(&store, 3, "job-b");
        record(&r, "job-b", 100..110);
        assert_eq!(sizes(&r), [("job-a".into(), 10), ("job-b".into(), 10)]);
        activated(&store, 4, "job-c");
        record(&r, "job-c", 200..210);
        assert_eq!(sizes(&r), [("job-a".into(), 4), ("job-b".into(), 10), ("job-c".into(), 10)]);
        activated(&store, 5, "job-d");
        record(&r, "job-d", 300..310);
        // Every older set at its floor before a set goes: an earlier domain stays guarded.
        assert_eq!(sizes(&r), [("job-a".into(), 4), ("job-b".into(), 4), ("job-c".into(), 6), ("job-d".into(), 10)]);
        activated(&store, 6, "job-e");
        record(&r, "job-e", 400..410);
        // ... and then the oldest goes.
        assert_eq!(sizes(&r), [("job-b".into(), 4), ("job-c".into(), 4), ("job-d".into(), 4), ("job-e".into(), 10)]);

        // A set is thinned for before its activation (the service's order): it counts already.
        record(&r, "job-g", 600..610);
        activated(&store, 8, "job-g");
        let total: usize = sizes(&r).iter().map(|(_, n)| n).sum();
        assert!(total <= 24, "{:?}", sizes(&r));

        // Anchor images: their own set, first, bounded, duplicates harmless.
        assert_eq!(r.put_anchor("car", b"anchor 1").unwrap(), (AckStatus::Accepted, 1));
        assert_eq!(r.put_anchor("car", b"anchor 1").unwrap(), (AckStatus::Duplicate, 1));
        assert_eq!(r.put_anchor("car", b"anchor 2").unwrap(), (AckStatus::Accepted, 2));
        assert_eq!(r.put_anchor("car", b"anchor 3").unwrap(), (AckStatus::Rejected, 2));
        let sets = r.sets("car").unwrap();
        assert_eq!((sets[0].set.set_id.as_str(), sets[0].set.kind, sets[0].shas.len()), (ANCHOR, SetKind::Anchor, 2));
        // Thinning never touches the anchor set.
        activated(&store, 7, "job-f");
        record(&r, "job-f", 500..510);
        assert_eq!(r.sets("car").unwrap()[0].shas.len(), 2);
        std::fs::remove_dir_all(&root).unwrap();
    }
}
