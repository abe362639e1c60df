//! The store (ARCHITECTURE.md "State"): everything the service writes, behind the
//! `object_store` crate, so one process on a local directory and a fleet on S3 share one design.
//!
//! ```text
//! models/<category>/versions/<version-id>/            weights + manifest.json (uploaded last)
//! models/<category>/activations/<generation:020>.json {version, previous, actor, reason, time, job_id?}
//! buffers/<category>/<sha256>.img, .json              target images (buffer.rs)
//! jobs/<job-id>/job.json, events/<seq:08>.json        adaptation jobs (jobs.rs)
//! ```
//!
//! Every write is create-only (`PutMode::Create`: a hard link on the local backend, with fsync;
//! `If-None-Match: *` on S3), nothing is rewritten in place, and a conditional write is the only
//! coordination between processes. The highest generation is the active version: activating
//! writes generation + 1, so of two writers racing for it exactly one wins. A version is
//! complete once its manifest (with the sha256 of every file) exists; anything else under
//! `versions/` is debris of a crash and is never served. The repository's `models/<category>/`
//! directories are read-only seeds, imported as `seed-<sha256(manifest)[:12]>`.
//!
//! The API is blocking (callers are worker threads, the job runner and `spawn_blocking`
//! closures); I/O runs on a small runtime of the store's own, so S3 calls never compete with
//! request handling.

use std::{
    fs,
    future::Future,
    path::{Path, PathBuf},
    sync::Arc,
    time::{Duration, SystemTime, UNIX_EPOCH},
};

use object_store::{
    ObjectStore, ObjectStoreExt, PutMode, PutOptions, PutPayload, aws::AmazonS3Builder, local::LocalFileSystem,
    path::Path as Key, prefix::PrefixStore,
};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use udapose_engine::checkpoint::{MANIFEST, Manifest};

/// Who imports seeds and activates them.
pub const SEED_ACTOR: &str = "seed";

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{key}: {source}")]
    Object {
        key: String,
        #[source]
        source: object_store::Error,
    },
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {reason}")]
    Corrupt { path: String, reason: String },
    #[error("invalid store {url:?}: {reason}")]
    Url { url: String, reason: String },
    #[error("the store {0} does not refuse a second create-only write of one object: it cannot coordinate writers")]
    NotCreateOnly(String),
    #[error("category {category}: version {version} does not exist")]
    UnknownVersion { category: String, version: String },
    #[error("category {category}: generation {found} is active, expected {expected}")]
    Conflict { category: String, expected: u64, found: u64 },
    #[error("category {0}: nothing to roll back to")]
    NoPrevious(String),
}

type Result<T> = std::result::Result<T, StoreError>;

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io { path: path.display().to_string(), source }
}

fn corrupt(path: impl Into<String>, reason: impl ToString) -> StoreError {
    StoreError::Corrupt { path: path.into(), reason: reason.to_string() }
}

/// One entry of a category's activation log.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Activation {
    pub version: String,
    /// What a rollback from this entry re-activates: the version active before it, or, for an
    /// entry a rollback wrote, the version that preceded its target (so rollbacks walk back).
    pub previous: Option<String>,
    pub actor: String,
    pub reason: String,
    /// Seconds since the Unix epoch.
    pub time: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job_id: Option<String>,
}

impl Activation {
    fn new(version: &str, previous: Option<String>, actor: &str, reason: &str, job_id: Option<&str>) -> Self {
        Activation {
            version: version.into(),
            previous,
            actor: actor.into(),
            reason: reason.into(),
            time: SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs()),
            job_id: job_id.map(str::to_owned),
        }
    }
}

/// `Conflict` unless `expected` (when given) is the active generation.
fn check_generation(category: &str, head: Option<&(u64, Activation)>, expected: Option<u64>) -> Result<()> {
    let found = head.map(|(g, _)| *g);
    match expected {
        Some(expected) if Some(expected) != found => {
            Err(StoreError::Conflict { category: category.into(), expected, found: found.unwrap_or(0) })
        }
        _ => Ok(()),
    }
}

/// Whether `name` may be a category: 1-64 of `[a-z0-9_-]`, starting with a letter or digit.
/// Anything else (`..`, `/`, upper case, empty) is refused before it becomes a key.
pub fn valid_category(name: &str) -> bool {
    let b = name.as_bytes();
    (1..=64).contains(&b.len())
        && b[0].is_ascii_alphanumeric()
        && b.iter().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == b'_' || *c == b'-')
}

/// How to reach an S3-compatible store; credentials come from the standard AWS environment.
#[derive(Clone, Debug, Default)]
pub struct S3Options {
    pub endpoint: Option<String>,
    pub region: Option<String>,
    pub allow_http: bool,
}

/// The objects directly under a prefix.
#[derive(Debug, Default)]
pub struct Listing {
    pub files: Vec<String>,
    pub dirs: Vec<String>,
}

/// A store: a local directory (`file:///path` or a plain path) or `s3://bucket/prefix`.
#[derive(Clone)]
pub struct Store {
    shared: Arc<Shared>,
}

struct Shared {
    objects: Arc<dyn ObjectStore>,
    runtime: Option<tokio::runtime::Runtime>,
    /// The directory of a local store: versions are loaded from it in place.
    local: Option<PathBuf>,
    /// Where versions of a remote store are downloaded to be loaded.
    cache: PathBuf,
    url: String,
}

impl Drop for Shared {
    fn drop(&mut self) {
        // Dropping a runtime blocks, which tokio forbids inside async code (the server's end).
        if let Some(rt) = self.runtime.take() {
            rt.shutdown_background();
        }
    }
}

impl std::fmt::Debug for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Store").field("url", &self.shared.url).finish()
    }
}

impl std::fmt::Display for Store {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.shared.url)
    }
}

impl Store {
    /// A local directory store (created if missing).
    #[cfg(test)]
    pub fn open(root: &Path) -> Result<Self> {
        Self::open_url(&root.display().to_string(), &S3Options::default(), &std::env::temp_dir())
    }

    /// Opens `url`; `cache` holds versions downloaded from a remote store.
    pub fn open_url(url: &str, s3: &S3Options, cache: &Path) -> Result<Self> {
        let bad = |reason: &dyn ToString| StoreError::Url { url: url.into(), reason: reason.to_string() };
        let (objects, local): (Arc<dyn ObjectStore>, _) = if let Some(rest) = url.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            if bucket.is_empty() {
                return Err(bad(&"no bucket: use s3://bucket/prefix"));
            }
            // reqwest is built without a default TLS provider: the service's is ring.
            let _ = rustls::crypto::ring::default_provider().install_default();
            let mut builder = AmazonS3Builder::from_env().with_bucket_name(bucket).with_allow_http(s3.allow_http);
            if let Some(endpoint) = &s3.endpoint {
                builder = builder.with_endpoint(endpoint);
            }
            if let Some(region) = &s3.region {
                builder = builder.with_region(region);
            }
            let s3 = builder.build().map_err(|e| bad(&e))?;
            let store: Arc<dyn ObjectStore> = match prefix.trim_matches('/') {
                "" => Arc::new(s3),
                p => Arc::new(PrefixStore::new(s3, p)),
            };
            (store, None)
        } else {
            let root = PathBuf::from(url.strip_prefix("file://").unwrap_or(url));
            if url.contains("://") && !url.starts_with("file://") {
                return Err(bad(&"unknown scheme: use file:///path, a path, or s3://bucket/prefix"));
            }
            fs::create_dir_all(&root).map_err(io_err(&root))?;
            let root = root.canonicalize().map_err(io_err(&root))?;
            let fs = LocalFileSystem::new_with_prefix(&root).map_err(|e| bad(&e))?.with_fsync(true);
            (Arc::new(fs) as Arc<dyn ObjectStore>, Some(root))
        };
        Self::with_objects(objects, local, cache, url)
    }

    /// A store held in memory (for tests and dry runs): nothing survives the process.
    pub fn in_memory(cache: &Path) -> Result<Self> {
        Store::with_objects(Arc::new(object_store::memory::InMemory::new()), None, cache, "memory://")
    }

    fn with_objects(objects: Arc<dyn ObjectStore>, local: Option<PathBuf>, cache: &Path, url: &str) -> Result<Self> {
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("store-io")
            .enable_all()
            .build()
            .map_err(io_err(Path::new("tokio runtime")))?;
        let cache = cache.join("udapose-versions");
        Ok(Store { shared: Arc::new(Shared { objects, runtime: Some(runtime), local, cache, url: url.into() }) })
    }

    /// Runs `f` on the store's runtime, from any thread (inside async code too).
    fn block<F: Future<Output: Send> + Send>(&self, f: F) -> F::Output {
        let rt = self.shared.runtime.as_ref().expect("the runtime lives as long as the store");
        match tokio::runtime::Handle::try_current() {
            Ok(h) if h.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread => {
                tokio::task::block_in_place(|| rt.block_on(f))
            }
            Ok(_) => std::thread::scope(|s| s.spawn(|| rt.block_on(f)).join().expect("store I/O panicked")),
            Err(_) => rt.block_on(f),
        }
    }

    fn object_err(key: &Key) -> impl FnOnce(object_store::Error) -> StoreError + '_ {
        move |source| StoreError::Object { key: key.to_string(), source }
    }

    /// Writes `key` only if it does not exist; false when it did (another writer won).
    pub fn create(&self, key: &str, bytes: Vec<u8>) -> Result<bool> {
        let key = Key::from(key);
        let opts = PutOptions { mode: PutMode::Create, ..Default::default() };
        match self.block(self.shared.objects.put_opts(&key, PutPayload::from(bytes), opts)) {
            Ok(_) => Ok(true),
            Err(object_store::Error::AlreadyExists { .. }) => Ok(false),
            Err(e) => Err(Self::object_err(&key)(e)),
        }
    }

    /// The object's bytes; `None` when it does not exist.
    pub fn read(&self, key: &str) -> Result<Option<Vec<u8>>> {
        let key = Key::from(key);
        let got = self.block(async {
            match self.shared.objects.get(&key).await {
                Ok(r) => r.bytes().await.map(Some),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(e),
            }
        });
        got.map(|b| b.map(|b| b.to_vec())).map_err(Self::object_err(&key))
    }

    pub fn exists(&self, key: &str) -> Result<bool> {
        let key = Key::from(key);
        match self.block(self.shared.objects.head(&key)) {
            Ok(_) => Ok(true),
            Err(object_store::Error::NotFound { .. }) => Ok(false),
            Err(e) => Err(Self::object_err(&key)(e)),
        }
    }

    /// A JSON object; `None` when it does not exist.
    pub fn read_json<T: serde::de::DeserializeOwned>(&self, key: &str) -> Result<Option<T>> {
        let Some(bytes) = self.read(key)? else { return Ok(None) };
        serde_json::from_slice(&bytes).map(Some).map_err(|e| corrupt(key, e))
    }

    /// The names directly under `prefix` (a "directory"): objects and sub-prefixes.
    pub fn list(&self, prefix: &str) -> Result<Listing> {
        let key = Key::from(prefix);
        let listed = self.block(self.shared.objects.list_with_delimiter(Some(&key)));
        let listed = match listed {
            Ok(l) => l,
            Err(object_store::Error::NotFound { .. }) => return Ok(Listing::default()),
            Err(e) => return Err(Self::object_err(&key)(e)),
        };
        let name = |p: &Key| p.filename().map(str::to_owned);
        let mut out = Listing {
            files: listed.objects.iter().filter_map(|o| name(&o.location)).collect(),
            dirs: listed.common_prefixes.iter().filter_map(name).collect(),
        };
        out.files.sort();
        out.dirs.sort();
        Ok(out)
    }

    /// Deletes `key` (gone already is fine).
    pub fn delete(&self, key: &str) -> Result<()> {
        let key = Key::from(key);
        match self.block(self.shared.objects.delete(&key)) {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(e) => Err(Self::object_err(&key)(e)),
        }
    }

    /// Checks that the store refuses a second create-only write of one object: the only
    /// coordination the service relies on (some S3-compatible servers ignore `If-None-Match`).
    pub fn probe(&self) -> Result<()> {
        let key = format!("probe/{}-{}.json", std::process::id(), nanos());
        let first = self.create(&key, b"{}".to_vec())?;
        let second = self.create(&key, b"{}".to_vec())?;
        self.delete(&key)?;
        if first && !second { Ok(()) } else { Err(StoreError::NotCreateOnly(self.shared.url.clone())) }
    }

    fn versions_key(category: &str) -> String {
        format!("models/{category}/versions")
    }

    fn activation_key(category: &str, generation: u64) -> String {
        format!("models/{category}/activations/{generation:020}.json")
    }

    /// Categories with an activation log, sorted.
    pub fn categories(&self) -> Result<Vec<String>> {
        let mut out = Vec::new();
        for name in self.list("models")?.dirs.into_iter().filter(|n| valid_category(n)) {
            if !self.generations(&name)?.is_empty() {
                out.push(name);
            }
        }
        Ok(out)
    }

    /// The active generation and its log entry; `None` when nothing was ever activated.
    pub fn head(&self, category: &str) -> Result<Option<(u64, Activation)>> {
        let Some(&generation) = self.generations(category)?.last() else { return Ok(None) };
        Ok(Some((generation, self.activation(category, generation)?)))
    }

    /// The generations in the log, ascending (names, not contents).
    fn generations(&self, category: &str) -> Result<Vec<u64>> {
        let files = self.list(&format!("models/{category}/activations"))?.files;
        let mut out: Vec<u64> =
            files.iter().filter_map(|n| n.strip_suffix(".json")).filter_map(|n| n.parse().ok()).collect();
        out.sort_unstable();
        Ok(out)
    }

    fn activation(&self, category: &str, generation: u64) -> Result<Activation> {
        let key = Self::activation_key(category, generation);
        self.read_json(&key)?.ok_or_else(|| corrupt(key, "listed but missing"))
    }

    /// The activation log, newest first.
    pub fn activations(&self, category: &str) -> Result<Vec<(u64, Activation)>> {
        let generations = self.generations(category)?;
        generations.into_iter().rev().map(|g| Ok((g, self.activation(category, g)?))).collect()
    }

    /// The manifest of a complete version.
    pub fn manifest(&self, category: &str, version: &str) -> Result<Manifest> {
        let key = format!("{}/{version}/{MANIFEST}", Self::versions_key(category));
        self.read_json(&key)?
            .ok_or_else(|| StoreError::UnknownVersion { category: category.into(), version: version.into() })
    }

    /// The complete versions of a category (manifest present), sorted by id.
    pub fn versions(&self, category: &str) -> Result<Vec<String>> {
        let prefix = Self::versions_key(category);
        let mut out = Vec::new();
        for v in self.list(&prefix)?.dirs.into_iter().filter(|v| !v.starts_with('.')) {
            if self.exists(&format!("{prefix}/{v}/{MANIFEST}"))? {
                out.push(v);
            }
        }
        Ok(out)
    }

    /// Activates `version` as the next generation, for `job_id` when a job's gate passed. With
    /// `expected_generation`, fails with `Conflict` unless that generation is the active one;
    /// a lost race is a `Conflict` too. Activating the active version writes nothing and
    /// returns its generation.
    pub fn activate(
        &self,
        category: &str,
        version: &str,
        actor: &str,
        reason: &str,
        expected_generation: Option<u64>,
        job_id: Option<&str>,
    ) -> Result<u64> {
        self.manifest(category, version)?;
        let head = self.head(category)?;
        check_generation(category, head.as_ref(), expected_generation)?;
        match head {
            Some((generation, active)) if active.version == version => Ok(generation),
            head => {
                let previous = head.as_ref().map(|(_, a)| a.version.clone());
                let entry = Activation::new(version, previous, actor, reason, job_id);
                self.append_activation(category, head.map(|(g, _)| g), entry)
            }
        }
    }

    /// Undoes the active entry: re-activates its `previous` version, and records as *that*
    /// entry's previous what was active before it, so that rollbacks walk back through the log
    /// (v1 → v2 → v3, rollback: v2, rollback: v1) instead of toggling.
    pub fn rollback(&self, category: &str, actor: &str, reason: &str, expected_generation: Option<u64>) -> Result<u64> {
        let no_previous = || StoreError::NoPrevious(category.into());
        let head = self.head(category)?.ok_or_else(no_previous)?;
        check_generation(category, Some(&head), expected_generation)?;
        let (generation, active) = head;
        let target = active.previous.ok_or_else(no_previous)?;
        self.manifest(category, &target)?;
        // The newest earlier entry that activated the target says what preceded it.
        let before = self
            .activations(category)?
            .into_iter()
            .find(|(g, a)| *g < generation && a.version == target)
            .and_then(|(_, a)| a.previous);
        self.append_activation(category, Some(generation), Activation::new(&target, before, actor, reason, None))
    }

    /// Writes `entry` as the generation after `current`, create-only (a lost race: `Conflict`).
    fn append_activation(&self, category: &str, current: Option<u64>, entry: Activation) -> Result<u64> {
        let generation = current.map_or(0, |g| g + 1);
        let bytes = serde_json::to_vec_pretty(&entry).expect("an activation serialises");
        if self.create(&Self::activation_key(category, generation), bytes)? {
            Ok(generation)
        } else {
            let found = self.head(category)?.map_or(0, |(g, _)| g);
            Err(StoreError::Conflict { category: category.into(), expected: current.unwrap_or(0), found })
        }
    }

    /// Writes a new version: `write` fills a local temporary directory, whose files are
    /// uploaded create-only, the manifest last, so the version appears complete or not at all.
    /// The version id belongs to its writer (a job): leftovers of its own crashed attempt are
    /// deleted first.
    pub fn put_version(
        &self,
        category: &str,
        version: &str,
        write: impl FnOnce(&Path) -> std::result::Result<(), String>,
    ) -> Result<()> {
        let prefix = format!("{}/{version}", Self::versions_key(category));
        if self.exists(&format!("{prefix}/{MANIFEST}"))? {
            return Err(corrupt(&prefix, "the version exists already"));
        }
        for file in self.list(&prefix)?.files {
            tracing::info!("removing debris {prefix}/{file}");
            self.delete(&format!("{prefix}/{file}"))?;
        }
        // `write` creates the directory itself (a model directory must not exist yet).
        let tmp = temp_sibling(&self.shared.cache.join(category).join(version));
        let parent = tmp.parent().expect("a temporary directory has a parent");
        fs::create_dir_all(parent).map_err(io_err(parent))?;
        let result = write(&tmp)
            .map_err(|reason| corrupt(tmp.display().to_string(), reason))
            .and_then(|()| self.upload_dir(&prefix, &tmp, Some("save-version")));
        let _ = fs::remove_dir_all(&tmp);
        result
    }

    /// Uploads a model directory's files under `prefix`, the manifest last (an object that
    /// exists already is kept: its name is its content's). `failpoint` fires before the manifest.
    fn upload_dir(&self, prefix: &str, dir: &Path, failpoint_name: Option<&str>) -> Result<()> {
        let mut files: Vec<PathBuf> = fs::read_dir(dir)
            .map_err(io_err(dir))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file() && p.file_name().is_some_and(|n| n != MANIFEST))
            .collect();
        files.sort();
        files.push(dir.join(MANIFEST));
        for (i, path) in files.iter().enumerate() {
            if i + 1 == files.len()
                && let Some(name) = failpoint_name
            {
                failpoint(name);
            }
            let name =
                path.file_name().and_then(|n| n.to_str()).ok_or_else(|| corrupt(path.display().to_string(), "name"))?;
            let bytes = fs::read(path).map_err(io_err(path))?;
            self.create(&format!("{prefix}/{name}"), bytes)?;
        }
        Ok(())
    }

    /// Imports the seed model directory `seed` for `category` (once: its id is content-derived)
    /// and activates it when the category has no activation yet, or when the active version
    /// is an older seed (the repository's model changed). Returns the seed's version id.
    pub fn import_seed(&self, category: &str, seed: &Path) -> Result<String> {
        let manifest_path = seed.join(MANIFEST);
        let manifest = fs::read(&manifest_path).map_err(io_err(&manifest_path))?;
        // A model copied into another category's folder would answer for the wrong object.
        let corrupt = |reason: String| StoreError::Corrupt { path: manifest_path.display().to_string(), reason };
        let parsed: Manifest = serde_json::from_slice(&manifest).map_err(|e| corrupt(e.to_string()))?;
        if parsed.category != category {
            return Err(corrupt(format!(
                "a model of category {:?} in the folder of category {category:?}",
                parsed.category
            )));
        }
        let digest: String = Sha256::digest(&manifest).iter().take(6).map(|b| format!("{b:02x}")).collect();
        let version = format!("seed-{digest}");
        let prefix = format!("{}/{version}", Self::versions_key(category));
        if !self.exists(&format!("{prefix}/{MANIFEST}"))? {
            self.upload_dir(&prefix, seed, None)?;
        }
        let replace = match self.head(category)? {
            None => true,
            Some((_, head)) => head.actor == SEED_ACTOR && head.version != version,
        };
        if replace {
            let reason = format!("imported seed {}", seed.display());
            match self.activate(category, &version, SEED_ACTOR, &reason, None, None) {
                Ok(_) | Err(StoreError::Conflict { .. }) => {} // another process imported it first
                Err(e) => return Err(e),
            }
        }
        Ok(version)
    }
}

/// A unique temporary sibling of `path`.
fn temp_sibling(path: &Path) -> PathBuf {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("tmp");
    path.with_file_name(format!(".{name}.{}.{}.tmp", std::process::id(), nanos()))
}

pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// Crash-test hook: with `UDAPOSE_FAILPOINT=<name>` the process stops for good at the point of
/// that name (logged), so a test can `kill -9` it exactly there; with `stop:<name>` it sends
/// itself SIGSTOP there (a test resumes it with SIGCONT). Only in builds with the `failpoints`
/// feature, which the end-to-end tests turn on (tests/Cargo.toml) and release builds lack.
#[cfg(not(feature = "failpoints"))]
pub(crate) fn failpoint(_name: &str) {}

/// Says at startup when `UDAPOSE_FAILPOINT` is set in a build that has no failpoints (it would
/// otherwise be ignored without a word).
pub fn check_failpoints() {
    if cfg!(not(feature = "failpoints")) && std::env::var_os("UDAPOSE_FAILPOINT").is_some() {
        tracing::warn!("UDAPOSE_FAILPOINT is set, but this build has no failpoints (`make test` builds them in)");
    }
}

#[cfg(feature = "failpoints")]
pub(crate) fn failpoint(name: &str) {
    let Ok(set) = std::env::var("UDAPOSE_FAILPOINT") else { return };
    if set == name {
        tracing::warn!("failpoint {name}: stopped here");
        loop {
            std::thread::sleep(std::time::Duration::from_secs(3600));
        }
    }
    if set.strip_prefix("stop:") == Some(name) {
        tracing::warn!("failpoint {name}: SIGSTOP");
        let _ = std::process::Command::new("kill").args(["-STOP", &std::process::id().to_string()]).status();
    }
}

pub(crate) fn nanos() -> u128 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos())
}

mod cache;
#[cfg(test)]
mod tests;
