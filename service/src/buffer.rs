//! The target-image buffer (ARCHITECTURE.md "State"): per category, acknowledged target images
//! in the store, named by the sha256 of their bytes.
//!
//! ```text
//! buffers/<category>/<sha256>.img    the image bytes, as received
//! buffers/<category>/<sha256>.json   written last: the image counts once this exists
//! ```
//!
//! Both are create-only writes, and an image is acknowledged only once its `.json` exists, so
//! nothing acknowledged is lost by a crash. An `.img` without its `.json` (a crash between the
//! two) is kept when the image comes again (same name, same bytes). Any replica may write here;
//! the adaptation worker reads.

use std::{
    collections::{BTreeSet, HashMap},
    sync::Mutex,
    time::{Duration, Instant},
};

use serde::{Deserialize, Serialize};

pub use crate::store::sha256_hex;
use crate::store::{Store, StoreError, nanos};

/// How long a category's image count is trusted before it is listed again (other replicas
/// add images too, so across replicas the capacity is approximate by this much).
const COUNT_TTL: Duration = Duration::from_secs(2);

/// What happened to one streamed image.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum AckStatus {
    Accepted,
    Duplicate,
    Rejected,
}

/// The durable record of a buffered image.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct TargetMeta {
    pub sha256: String,
    pub bytes: u64,
    pub width: u32,
    pub height: u32,
    /// Seconds since the Unix epoch.
    pub received: f64,
}

/// The categories' buffered images in the store, each bounded by `capacity`.
pub struct Buffer {
    store: Store,
    pub capacity: usize,
    /// Image counts per category and when they were listed; the lock also serialises puts, so
    /// the capacity check and the write are one step in this process.
    counts: Mutex<HashMap<String, (usize, Instant)>>,
}

impl Buffer {
    pub fn new(store: Store, capacity: usize) -> Self {
        Buffer { store, capacity, counts: Mutex::new(HashMap::new()) }
    }

    fn key(category: &str, sha: &str, ext: &str) -> String {
        format!("buffers/{category}/{sha}.{ext}")
    }

    fn counts(&self) -> std::sync::MutexGuard<'_, HashMap<String, (usize, Instant)>> {
        self.counts.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The number of buffered images of `category`, listed at most every `COUNT_TTL`.
    pub fn count(&self, category: &str) -> Result<usize, StoreError> {
        let mut counts = self.counts();
        Self::count_locked(self, &mut counts, category)
    }

    fn count_locked(
        &self,
        counts: &mut HashMap<String, (usize, Instant)>,
        category: &str,
    ) -> Result<usize, StoreError> {
        match counts.get(category) {
            Some(&(n, at)) if at.elapsed() < COUNT_TTL => Ok(n),
            _ => {
                let n = self.list(category)?.len();
                counts.insert(category.to_owned(), (n, Instant::now()));
                Ok(n)
            }
        }
    }

    /// Stores `bytes` (already decoded and checked by the caller) unless the buffer is full.
    /// Returns the status and the number of images buffered afterwards.
    pub fn put(&self, category: &str, bytes: &[u8], width: u32, height: u32) -> Result<(AckStatus, usize), StoreError> {
        let mut counts = self.counts();
        let sha = sha256_hex(bytes);
        let count = self.count_locked(&mut counts, category)?;
        if self.store.exists(&Self::key(category, &sha, "json"))? {
            return Ok((AckStatus::Duplicate, count));
        }
        if count >= self.capacity {
            return Ok((AckStatus::Rejected, count));
        }
        // A leftover `.img` holds these very bytes (its name is their hash): create keeps it.
        self.store.create(&Self::key(category, &sha, "img"), bytes.to_vec())?;
        let meta = TargetMeta {
            sha256: sha.clone(),
            bytes: bytes.len() as u64,
            width,
            height,
            received: nanos() as f64 / 1e9,
        };
        let json = serde_json::to_vec_pretty(&meta).expect("a target record serialises");
        self.store.create(&Self::key(category, &sha, "json"), json)?;
        if let Some((n, _)) = counts.get_mut(category) {
            *n += 1;
        }
        Ok((AckStatus::Accepted, count + 1))
    }

    /// The sha256 ids of the category's complete (acknowledged) images, sorted.
    pub fn list(&self, category: &str) -> Result<BTreeSet<String>, StoreError> {
        let files = self.store.list(&format!("buffers/{category}"))?.files;
        Ok(files
            .iter()
            .filter_map(|n| n.strip_suffix(".json"))
            .filter(|sha| sha.len() == 64 && sha.bytes().all(|b| b.is_ascii_hexdigit()))
            .map(str::to_owned)
            .collect())
    }

    pub fn read(&self, category: &str, sha: &str) -> Result<Vec<u8>, StoreError> {
        let key = Self::key(category, sha, "img");
        self.store.read(&key)?.ok_or_else(|| StoreError::Corrupt { path: key, reason: "missing".into() })
    }

    /// Drops images a finished job used: the `.json` first, so a crash in between leaves an
    /// unacknowledged `.img` that nothing counts.
    pub fn remove(&self, category: &str, shas: &[String]) {
        let mut counts = self.counts();
        for sha in shas {
            for ext in ["json", "img"] {
                if let Err(e) = self.store.delete(&Self::key(category, sha, ext)) {
                    tracing::warn!("cannot remove a buffered image: {e}");
                }
            }
        }
        counts.remove(category);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn images_are_acknowledged_once_and_bounded() {
        let root = std::env::temp_dir().join(format!("udapose-buffer-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let store = Store::open(&root).unwrap();
        let buffer = Buffer::new(store.clone(), 2);
        assert_eq!(buffer.put("car", b"one", 1, 1).unwrap(), (AckStatus::Accepted, 1));
        assert_eq!(buffer.put("car", b"one", 1, 1).unwrap(), (AckStatus::Duplicate, 1));
        // A crash between the image and its record: the image is not counted, and a resend
        // completes it.
        let sha = sha256_hex(b"two");
        store.create(&format!("buffers/car/{sha}.img"), b"two".to_vec()).unwrap();
        assert_eq!(buffer.list("car").unwrap().len(), 1);
        assert_eq!(buffer.put("car", b"two", 1, 1).unwrap(), (AckStatus::Accepted, 2));
        assert_eq!(buffer.put("car", b"three", 1, 1).unwrap(), (AckStatus::Rejected, 2));
        assert_eq!(buffer.read("car", &sha).unwrap(), b"two");
        buffer.remove("car", &[sha]);
        assert_eq!(buffer.list("car").unwrap().len(), 1);
        assert_eq!(buffer.put("car", b"three", 1, 1).unwrap(), (AckStatus::Accepted, 2));
        std::fs::remove_dir_all(&root).unwrap();
    }
}
