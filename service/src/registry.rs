//! The in-memory model registry: per category, the active version (an `ArcSwap`, never
//! tensors), the bounded queue in front of its inference workers, and their load state.
//!
//! Swapping a model is publishing a new `ActiveVersion`: each worker notices the new generation
//! between batches, loads its own copy, and answers with the version that computed each
//! answer (ARCHITECTURE.md "Threading with tch"). Requests already in a batch finish on the
//! old version.

use std::{
    collections::BTreeMap,
    fs,
    path::{Path, PathBuf},
    sync::{
        Arc, Mutex,
        atomic::{AtomicUsize, Ordering},
    },
    time::Duration,
};

use anyhow::{Context, Result};
use arc_swap::ArcSwapOption;
use crossbeam_channel::{Sender, TrySendError};
use udapose_engine::{
    checkpoint::{MANIFEST, Manifest},
    signature::Domain,
};

use crate::{
    error::ApiError,
    metrics::Metrics,
    store::{Store, StoreError, valid_category},
    worker::{self, Request, WorkerConfig},
};

/// The version a category serves: what a worker needs to load its own copy.
#[derive(Debug, Clone)]
pub struct ActiveVersion {
    pub version: String,
    pub generation: u64,
    pub dir: PathBuf,
    pub manifest: Manifest,
    /// The manifest's experts with a local directory each (empty for a plain version).
    pub experts: Vec<ExpertVersion>,
}

/// An expert of the active version, ready to load.
#[derive(Debug, Clone)]
pub struct ExpertVersion {
    pub version: String,
    pub domain: Domain,
    pub dir: PathBuf,
}

/// One category: its active version, its queue and its workers' state.
pub struct Category {
    pub name: String,
    active: ArcSwapOption<ActiveVersion>,
    workers: usize,
    /// Workers holding a loaded model (of any generation).
    loaded: AtomicUsize,
    /// Why the model is not being served, when it is not.
    error: Mutex<Option<String>>,
    queue: Sender<Request>,
    capacity: usize,
}

impl Category {
    pub fn active(&self) -> Option<Arc<ActiveVersion>> {
        self.active.load_full()
    }

    /// Every worker has a model loaded.
    pub fn ready(&self) -> bool {
        self.loaded.load(Ordering::Acquire) == self.workers && self.error().is_none()
    }

    pub fn error(&self) -> Option<String> {
        self.error.lock().map(|e| e.clone()).unwrap_or_else(|p| p.into_inner().clone())
    }

    pub(crate) fn set_error(&self, error: Option<String>) {
        match self.error.lock() {
            Ok(mut e) => *e = error,
            Err(p) => *p.into_inner() = error,
        }
    }

    pub(crate) fn worker_loaded(&self) {
        self.loaded.fetch_add(1, Ordering::AcqRel);
    }

    /// Jobs waiting for a worker.
    pub fn queued(&self) -> usize {
        self.queue.len()
    }

    /// Whether a new request would be refused right now (checked before decoding, to fail fast).
    pub fn saturated(&self) -> bool {
        self.queue.len() >= self.capacity
    }

    /// Admits a request or refuses it at once: the queue is bounded, never waited on.
    pub fn submit(&self, request: Request) -> Result<(), ApiError> {
        if !self.ready() {
            let why = self.error().unwrap_or_else(|| "still loading".into());
            return Err(ApiError::unavailable(format!("the {} model is not ready: {why}", self.name)));
        }
        match self.queue.try_send(request) {
            Ok(()) => Ok(()),
            Err(TrySendError::Full(_)) => Err(ApiError::unavailable(format!(
                "overloaded: the {} queue is full ({} waiting); retry later",
                self.name, self.capacity
            ))),
            Err(TrySendError::Disconnected(_)) => Err(ApiError::Internal("the inference workers stopped".into())),
        }
    }

    /// Re-reads the activation log and publishes its head if it changed (the hot-swap path that
    /// adaptation jobs and replicas polling the store use). Returns whether it changed.
    /// Only the log is read while nothing changed (the manifest and the download come with a
    /// new generation).
    pub fn refresh(&self, store: &Store) -> Result<bool, StoreError> {
        let head = store.head(&self.name)?;
        if self.active().map(|a| a.generation) == head.as_ref().map(|(g, _)| *g) {
            return Ok(false);
        }
        let next = head.map(|head| active_version(store, &self.name, head)).transpose()?;
        self.active.store(next.map(Arc::new));
        Ok(true)
    }
}

fn read_active(store: &Store, category: &str) -> Result<Option<ActiveVersion>, StoreError> {
    store.head(category)?.map(|head| active_version(store, category, head)).transpose()
}

/// The log's head as a version to serve: its manifest, and a local directory holding it.
fn active_version(
    store: &Store,
    category: &str,
    (generation, head): (u64, crate::store::Activation),
) -> Result<ActiveVersion, StoreError> {
    let manifest = store.manifest(category, &head.version)?;
    let dir = store.version_dir(category, &head.version)?;
    let experts = manifest
        .experts
        .iter()
        .map(|e| {
            let dir = store.version_dir(category, &e.version)?;
            Ok(ExpertVersion { version: e.version.clone(), domain: e.domain.clone(), dir })
        })
        .collect::<Result<_, StoreError>>()?;
    Ok(ActiveVersion { version: head.version, generation, dir, manifest, experts })
}

/// Whether every configured model is loaded, and why not.
#[derive(Debug, PartialEq, Eq)]
pub struct Readiness {
    pub ready: bool,
    pub reason: String,
}

/// Every category the server serves.
pub struct Registry {
    store: Store,
    categories: BTreeMap<String, Arc<Category>>,
}

impl Registry {
    /// Imports the seeds under `seeds` into the store, then starts the workers of every
    /// category the store has (each loads its model on its own thread: readiness follows).
    pub fn start(store: Store, seeds: &Path, config: &WorkerConfig, metrics: Arc<Metrics>) -> Result<Self> {
        let mut seed_errors = BTreeMap::new();
        for (category, dir) in seed_dirs(seeds)? {
            if let Err(e) = store.import_seed(&category, &dir) {
                tracing::warn!(%category, "cannot import seed {}: {e}", dir.display());
                seed_errors.insert(category, e.to_string());
            }
        }
        let mut names = store.categories().context("listing the store's categories")?;
        for failed in seed_errors.keys() {
            if !names.contains(failed) {
                names.push(failed.clone());
            }
        }
        names.sort();
        let mut categories = BTreeMap::new();
        for name in names {
            let active = read_active(&store, &name);
            let (tx, rx) = crossbeam_channel::bounded(config.queue_depth);
            let error = match (&active, seed_errors.get(&name)) {
                (Err(e), _) => Some(e.to_string()),
                (Ok(None), Some(e)) => Some(e.clone()),
                (Ok(None), None) => Some("no active version".into()),
                (Ok(Some(_)), _) => None,
            };
            let category = Arc::new(Category {
                name: name.clone(),
                active: ArcSwapOption::new(active.ok().flatten().map(Arc::new)),
                workers: config.workers,
                loaded: AtomicUsize::new(0),
                error: Mutex::new(error),
                queue: tx,
                capacity: config.queue_depth,
            });
            if category.active().is_some() {
                for i in 0..config.workers {
                    worker::spawn(category.clone(), rx.clone(), config.clone(), metrics.clone(), i)?;
                }
            }
            categories.insert(name, category);
        }
        Ok(Registry { store, categories })
    }

    pub fn store(&self) -> &Store {
        &self.store
    }

    pub fn get(&self, name: &str) -> Option<&Arc<Category>> {
        self.categories.get(name)
    }

    pub fn categories(&self) -> impl Iterator<Item = &Arc<Category>> {
        self.categories.values()
    }

    /// Re-reads every category's activation log; workers swap to a new head between batches.
    pub fn refresh(&self) {
        for c in self.categories() {
            match c.refresh(&self.store) {
                Ok(true) => {
                    tracing::info!(category = %c.name, version = ?c.active().map(|a| a.version.clone()), "new active version")
                }
                Ok(false) => {}
                Err(e) => tracing::warn!(category = %c.name, "reading the activation log: {e}"),
            }
        }
    }

    /// Polls the store every `period` (other processes may activate versions).
    pub fn poll(self: &std::sync::Arc<Self>, period: Duration) {
        let registry = std::sync::Arc::downgrade(self);
        std::thread::Builder::new()
            .name("store-poll".into())
            .spawn(move || {
                loop {
                    std::thread::sleep(period);
                    let Some(r) = registry.upgrade() else { return };
                    r.refresh();
                }
            })
            .expect("spawning the store poller");
    }

    /// Ready only when at least one model is configured and all are loaded.
    pub fn readiness(&self) -> Readiness {
        let total = self.categories.len();
        let loaded = self.categories().filter(|c| c.ready()).count();
        let reason = if total == 0 {
            "no models loaded: none configured".to_string()
        } else if loaded == total {
            format!("{loaded} of {total} models loaded")
        } else {
            let pending: Vec<String> = self
                .categories()
                .filter(|c| !c.ready())
                .map(|c| format!("{}: {}", c.name, c.error().unwrap_or_else(|| "loading".into())))
                .collect();
            format!("{loaded} of {total} models loaded; not ready: {}", pending.join("; "))
        };
        Readiness { ready: total > 0 && loaded == total, reason }
    }
}

/// `<seeds>/<category>/` directories holding a manifest, sorted; a missing `seeds` means none.
fn seed_dirs(seeds: &Path) -> Result<Vec<(String, PathBuf)>> {
    if !seeds.exists() {
        tracing::warn!("seed models directory {} does not exist", seeds.display());
        return Ok(Vec::new());
    }
    anyhow::ensure!(seeds.is_dir(), "models path {} is not a directory", seeds.display());
    let mut out = Vec::new();
    for entry in fs::read_dir(seeds).with_context(|| format!("reading {}", seeds.display()))? {
        let path = entry.with_context(|| format!("listing {}", seeds.display()))?.path();
        if !path.join(MANIFEST).is_file() {
            continue;
        }
        match path.file_name().and_then(|n| n.to_str()).filter(|n| valid_category(n)) {
            Some(name) => out.push((name.to_owned(), path.clone())),
            None => tracing::warn!("skipping model directory {path:?}: not a valid category name ([a-z0-9_-])"),
        }
    }
    out.sort();
    Ok(out)
}

#[cfg(test)]
mod tests;
