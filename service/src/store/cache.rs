//! The local cache of a remote store's versions: verified downloads, kept by last use.

use super::*;

/// Downloaded versions kept per category in the cache (the newest by last use): the active one,
/// a rollback target, a job's source. Older ones are deleted, and downloaded again if ever
/// needed, so a replica that hot-swaps for months does not fill its disk.
const CACHE_KEEP: usize = 3;
/// A cached version used this recently is never deleted: a thread (or another process sharing
/// the cache) may be loading it from there right now.
const CACHE_GRACE: Duration = Duration::from_secs(600);

impl Store {
    /// A local directory holding the complete version, to load it from: the version itself in
    /// a local store; a verified download (files checked against the manifest's sha256, the
    /// manifest written last, then renamed into place) from a remote one.
    pub fn version_dir(&self, category: &str, version: &str) -> Result<PathBuf> {
        if let Some(root) = &self.shared.local {
            return Ok(root.join(Self::versions_key(category)).join(version));
        }
        let dir = self.shared.cache.join(category).join(version);
        if dir.join(MANIFEST).is_file() {
            touch(&dir);
            return Ok(dir);
        }
        let prefix = format!("{}/{version}", Self::versions_key(category));
        let manifest_key = format!("{prefix}/{MANIFEST}");
        let manifest_bytes = self
            .read(&manifest_key)?
            .ok_or_else(|| StoreError::UnknownVersion { category: category.into(), version: version.into() })?;
        let manifest: Manifest = serde_json::from_slice(&manifest_bytes).map_err(|e| corrupt(&manifest_key, e))?;
        let tmp = temp_sibling(&dir);
        fs::create_dir_all(&tmp).map_err(io_err(&tmp))?;
        let result = (|| {
            for (file, sha) in &manifest.files {
                let key = format!("{prefix}/{file}");
                if file.contains('/') || file.starts_with('.') {
                    return Err(corrupt(&key, "not a plain file name"));
                }
                let bytes = self.read(&key)?.ok_or_else(|| corrupt(&key, "listed in the manifest but missing"))?;
                if &sha256_hex(&bytes) != sha {
                    return Err(corrupt(&key, "does not match its sha256 in the manifest"));
                }
                fs::write(tmp.join(file), bytes).map_err(io_err(&tmp))?;
            }
            fs::write(tmp.join(MANIFEST), &manifest_bytes).map_err(io_err(&tmp))?;
            match fs::rename(&tmp, &dir) {
                Ok(()) => Ok(()),
                Err(_) if dir.join(MANIFEST).is_file() => Ok(()), // another thread got it first
                Err(e) => Err(io_err(&dir)(e)),
            }
        })();
        let _ = fs::remove_dir_all(&tmp);
        result?;
        touch(&dir);
        self.prune_cache(category);
        Ok(dir)
    }

    /// Deletes the cached versions of `category` beyond the `CACHE_KEEP` last used, except any
    /// used within `CACHE_GRACE`, and temporary directories that old (left by a crash). Best
    /// effort: a failure only costs disk space, so it is logged.
    fn prune_cache(&self, category: &str) {
        let parent = self.shared.cache.join(category);
        let Ok(entries) = fs::read_dir(&parent) else { return };
        let (mut cached, mut old) = (Vec::new(), Vec::new());
        let cutoff = SystemTime::now() - CACHE_GRACE;
        for e in entries.filter_map(|e| e.ok()) {
            let Some(used) = e.metadata().ok().and_then(|m| m.modified().ok()) else { continue };
            if !e.file_name().to_string_lossy().starts_with('.') {
                cached.push((used, e.path()));
            } else if used < cutoff {
                old.push(e.path());
            }
        }
        cached.sort_by_key(|(used, _)| std::cmp::Reverse(*used));
        old.extend(cached.into_iter().skip(CACHE_KEEP).filter(|(used, _)| *used < cutoff).map(|(_, dir)| dir));
        for dir in old {
            match fs::remove_dir_all(&dir) {
                Ok(()) => tracing::info!(dir = %dir.display(), "removed from the version cache"),
                Err(e) => tracing::warn!(dir = %dir.display(), "could not remove from the version cache: {e}"),
            }
        }
    }
}

/// Marks a cached version as just used (its directory's mtime), for `prune_cache`.
fn touch(dir: &Path) {
    if let Err(e) = fs::File::open(dir).and_then(|f| f.set_modified(SystemTime::now())) {
        tracing::warn!(dir = %dir.display(), "could not mark a cached version as used: {e}");
    }
}
