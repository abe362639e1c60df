//! The target-image buffer (ARCHITECTURE.md "State"): per category, acknowledged target images
//! on disk, named by the sha256 of their bytes.
//!
//! ```text
//! <root>/buffers/<category>/<sha256>.img    the image bytes, as received
//! <root>/buffers/<category>/<sha256>.json   written last: the image counts once this exists
//! ```
//!
//! Both files are create-only writes (synced, then hard-linked into place), and an image is
//! acknowledged only once its `.json` exists, so nothing acknowledged is lost by a crash. An
//! `.img` without its `.json` (a crash between the two) is reused when the image comes again.

use std::{
    collections::BTreeSet,
    fs, io,
    path::{Path, PathBuf},
    sync::Mutex,
};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::store::{create_only, nanos};

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

/// One category's buffered images on disk, bounded by `capacity`.
pub struct Buffer {
    root: PathBuf,
    pub capacity: usize,
    /// Serialises puts, so the capacity check and the write are one step in this process.
    lock: Mutex<()>,
}

pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

impl Buffer {
    pub fn new(store_root: &Path, capacity: usize) -> Self {
        Buffer { root: store_root.join("buffers"), capacity, lock: Mutex::new(()) }
    }

    fn dir(&self, category: &str) -> PathBuf {
        self.root.join(category)
    }

    /// Stores `bytes` (already decoded and checked by the caller) unless the buffer is full.
    /// Returns the status and the number of images buffered afterwards.
    pub fn put(&self, category: &str, bytes: &[u8], width: u32, height: u32) -> io::Result<(AckStatus, usize)> {
        let _guard = self.lock.lock().unwrap_or_else(|p| p.into_inner());
        let sha = sha256_hex(bytes);
        let dir = self.dir(category);
        let meta_path = dir.join(format!("{sha}.json"));
        let count = self.list(category)?.len();
        if meta_path.is_file() {
            return Ok((AckStatus::Duplicate, count));
        }
        if count >= self.capacity {
            return Ok((AckStatus::Rejected, count));
        }
        fs::create_dir_all(&dir)?;
        // A leftover `.img` holds these very bytes (its name is their hash): create_only keeps it.
        create_only(&dir.join(format!("{sha}.img")), bytes)?;
        let meta = TargetMeta {
            sha256: sha.clone(),
            bytes: bytes.len() as u64,
            width,
            height,
            received: nanos() as f64 / 1e9,
        };
        let json = serde_json::to_vec_pretty(&meta).map_err(io::Error::other)?;
        create_only(&meta_path, &json)?;
        Ok((AckStatus::Accepted, count + 1))
    }

    /// The sha256 ids of the category's complete (acknowledged) images, sorted.
    pub fn list(&self, category: &str) -> io::Result<BTreeSet<String>> {
        let dir = self.dir(category);
        let mut out = BTreeSet::new();
        let entries = match fs::read_dir(&dir) {
            Ok(e) => e,
            Err(e) if e.kind() == io::ErrorKind::NotFound => return Ok(out),
            Err(e) => return Err(e),
        };
        for entry in entries {
            let name = entry?.file_name();
            if let Some(sha) = name.to_str().and_then(|n| n.strip_suffix(".json"))
                && sha.len() == 64
                && sha.bytes().all(|b| b.is_ascii_hexdigit())
            {
                out.insert(sha.to_owned());
            }
        }
        Ok(out)
    }

    pub fn read(&self, category: &str, sha: &str) -> io::Result<Vec<u8>> {
        fs::read(self.dir(category).join(format!("{sha}.img")))
    }

    /// Drops images a finished job used: the `.json` first, so a crash in between leaves an
    /// unacknowledged `.img` that nothing counts.
    pub fn remove(&self, category: &str, shas: &[String]) {
        let _guard = self.lock.lock().unwrap_or_else(|p| p.into_inner());
        let dir = self.dir(category);
        for sha in shas {
            for ext in ["json", "img"] {
                let path = dir.join(format!("{sha}.{ext}"));
                if let Err(e) = fs::remove_file(&path)
                    && e.kind() != io::ErrorKind::NotFound
                {
                    tracing::warn!("cannot remove {}: {e}", path.display());
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn images_are_acknowledged_once_and_bounded() {
        let root = std::env::temp_dir().join(format!("udapose-buffer-{}", std::process::id()));
        let _ = fs::remove_dir_all(&root);
        let buffer = Buffer::new(&root, 2);
        assert_eq!(buffer.put("car", b"one", 1, 1).unwrap(), (AckStatus::Accepted, 1));
        assert_eq!(buffer.put("car", b"one", 1, 1).unwrap(), (AckStatus::Duplicate, 1));
        // A crash between the image and its record: the image is not counted, and a resend
        // completes it.
        let sha = sha256_hex(b"two");
        create_only(&root.join(format!("buffers/car/{sha}.img")), b"two").unwrap();
        assert_eq!(buffer.list("car").unwrap().len(), 1);
        assert_eq!(buffer.put("car", b"two", 1, 1).unwrap(), (AckStatus::Accepted, 2));
        assert_eq!(buffer.put("car", b"three", 1, 1).unwrap(), (AckStatus::Rejected, 2));
        assert_eq!(buffer.read("car", &sha).unwrap(), b"two");
        buffer.remove("car", &[sha]);
        assert_eq!(buffer.list("car").unwrap().len(), 1);
        assert_eq!(buffer.put("car", b"three", 1, 1).unwrap(), (AckStatus::Accepted, 2));
        fs::remove_dir_all(&root).unwrap();
    }
}
