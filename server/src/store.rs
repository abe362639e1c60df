//! The model store on disk (ARCHITECTURE.md "State"): immutable version directories and an
//! append-only activation log per category, every write create-only.
//!
//! ```text
//! <root>/models/<category>/versions/<version-id>/        manifest.json + weights, never rewritten
//! <root>/models/<category>/activations/<generation:020>.json   {version, previous, actor, reason, time}
//! ```
//!
//! The highest generation is the active version. Activating writes generation + 1 with a
//! create-only write (hard link of a synced temporary file), so two writers cannot both win.
//! The repository's `models/<category>/` directories are read-only seeds, imported as
//! `seed-<sha256(manifest)[:12]>`.

use std::{
    fs::{self, File},
    io::{self, Write},
    path::{Path, PathBuf},
    time::{SystemTime, UNIX_EPOCH},
};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use udapose_engine::checkpoint::{MANIFEST, Manifest};

/// Who imports seeds and activates them.
pub const SEED_ACTOR: &str = "seed";

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("{path}: {source}")]
    Io {
        path: String,
        #[source]
        source: io::Error,
    },
    #[error("{path}: {reason}")]
    Corrupt { path: String, reason: String },
    #[error("category {category}: version {version} does not exist")]
    UnknownVersion { category: String, version: String },
    #[error("category {category}: generation {found} is active, expected {expected}")]
    Conflict { category: String, expected: u64, found: u64 },
    #[error("category {0}: nothing to roll back to")]
    NoPrevious(String),
}

type Result<T> = std::result::Result<T, StoreError>;

fn io_err(path: &Path) -> impl FnOnce(io::Error) -> StoreError + '_ {
    move |source| StoreError::Io { path: path.display().to_string(), source }
}

/// One entry of a category's activation log.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Activation {
    pub version: String,
    /// The version active before this one (what a rollback re-activates).
    pub previous: Option<String>,
    pub actor: String,
    pub reason: String,
    /// Seconds since the Unix epoch.
    pub time: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub job_id: Option<String>,
}

/// Whether `name` may be a category: 1-64 of `[a-z0-9_-]`, starting with a letter or digit.
/// Anything else (`..`, `/`, upper case, empty) is refused before it touches a path.
pub fn valid_category(name: &str) -> bool {
    let b = name.as_bytes();
    (1..=64).contains(&b.len())
        && b[0].is_ascii_alphanumeric()
        && b.iter().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || *c == b'_' || *c == b'-')
}

/// A local-directory store.
#[derive(Debug, Clone)]
pub struct Store {
    root: PathBuf,
}

impl Store {
    /// Opens (creating) the store at `root`.
    pub fn open(root: &Path) -> Result<Self> {
        let models = root.join("models");
        fs::create_dir_all(&models).map_err(io_err(&models))?;
        Ok(Store { root: root.to_path_buf() })
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    fn category_dir(&self, category: &str) -> PathBuf {
        self.root.join("models").join(category)
    }

    pub fn version_dir(&self, category: &str, version: &str) -> PathBuf {
        self.category_dir(category).join("versions").join(version)
    }

    fn activations_dir(&self, category: &str) -> PathBuf {
        self.category_dir(category).join("activations")
    }

    /// Categories with an activation log, sorted.
    pub fn categories(&self) -> Result<Vec<String>> {
        let dir = self.root.join("models");
        let mut out = Vec::new();
        for entry in fs::read_dir(&dir).map_err(io_err(&dir))? {
            let entry = entry.map_err(io_err(&dir))?;
            if let Some(name) = entry.file_name().to_str().filter(|n| valid_category(n))
                && entry.path().join("activations").is_dir()
            {
                out.push(name.to_owned());
            }
        }
        out.sort();
        Ok(out)
    }

    /// The active generation and its log entry; `None` when nothing was ever activated.
    pub fn head(&self, category: &str) -> Result<Option<(u64, Activation)>> {
        let Some(&generation) = self.generations(category)?.last() else { return Ok(None) };
        Ok(Some((generation, self.activation(category, generation)?)))
    }

    /// The generations in the log, ascending (file names, not contents).
    fn generations(&self, category: &str) -> Result<Vec<u64>> {
        let dir = self.activations_dir(category);
        if !dir.is_dir() {
            return Ok(Vec::new());
        }
        let mut out = Vec::new();
        for entry in fs::read_dir(&dir).map_err(io_err(&dir))? {
            let name = entry.map_err(io_err(&dir))?.file_name();
            out.extend(name.to_str().and_then(|n| n.strip_suffix(".json")).and_then(|n| n.parse::<u64>().ok()));
        }
        out.sort_unstable();
        Ok(out)
    }

    fn activation(&self, category: &str, generation: u64) -> Result<Activation> {
        let path = self.activations_dir(category).join(activation_name(generation));
        let text = fs::read_to_string(&path).map_err(io_err(&path))?;
        serde_json::from_str(&text)
            .map_err(|e| StoreError::Corrupt { path: path.display().to_string(), reason: e.to_string() })
    }

    /// The manifest of a complete version (its manifest is written last; a directory without
    /// one is debris from a crash and does not count).
    pub fn manifest(&self, category: &str, version: &str) -> Result<Manifest> {
        let path = self.version_dir(category, version).join(MANIFEST);
        if !path.is_file() {
            return Err(StoreError::UnknownVersion { category: category.into(), version: version.into() });
        }
        let text = fs::read_to_string(&path).map_err(io_err(&path))?;
        serde_json::from_str(&text)
            .map_err(|e| StoreError::Corrupt { path: path.display().to_string(), reason: e.to_string() })
    }

    /// Activates `version` as the next generation. With `expected_generation`, fails with
    /// `Conflict` unless that generation is the active one; a lost race is a `Conflict` too.
    pub fn activate(
        &self,
        category: &str,
        version: &str,
        actor: &str,
        reason: &str,
        expected_generation: Option<u64>,
    ) -> Result<u64> {
        self.activate_for_job(category, version, actor, reason, expected_generation, None)
    }

    /// [`Store::activate`], recording the adaptation job whose gate passed.
    pub fn activate_for_job(
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
        let current = head.as_ref().map(|(g, _)| *g);
        if let (Some(expected), found) = (expected_generation, current)
            && Some(expected) != found
        {
            return Err(StoreError::Conflict { category: category.into(), expected, found: found.unwrap_or(0) });
        }
        let generation = current.map_or(0, |g| g + 1);
        let activation = Activation {
            version: version.into(),
            previous: head.map(|(_, a)| a.version),
            actor: actor.into(),
            reason: reason.into(),
            time: SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs()),
            job_id: job_id.map(str::to_owned),
        };
        let dir = self.activations_dir(category);
        fs::create_dir_all(&dir).map_err(io_err(&dir))?;
        let bytes = serde_json::to_vec_pretty(&activation).expect("an activation serialises");
        let path = dir.join(activation_name(generation));
        if create_only(&path, &bytes).map_err(io_err(&path))? {
            Ok(generation)
        } else {
            let found = self.head(category)?.map_or(0, |(g, _)| g);
            Err(StoreError::Conflict { category: category.into(), expected: current.unwrap_or(0), found })
        }
    }

    /// The activation log, newest first.
    pub fn activations(&self, category: &str) -> Result<Vec<(u64, Activation)>> {
        let generations = self.generations(category)?;
        generations.into_iter().rev().map(|g| Ok((g, self.activation(category, g)?))).collect()
    }

    /// The complete versions of a category (manifest present), sorted by id.
    pub fn versions(&self, category: &str) -> Result<Vec<String>> {
        let dir = self.category_dir(category).join("versions");
        if !dir.is_dir() {
            return Ok(Vec::new());
        }
        let mut out = Vec::new();
        for entry in fs::read_dir(&dir).map_err(io_err(&dir))? {
            let entry = entry.map_err(io_err(&dir))?;
            if let Some(name) = entry.file_name().to_str().filter(|n| !n.starts_with('.'))
                && entry.path().join(MANIFEST).is_file()
            {
                out.push(name.to_owned());
            }
        }
        out.sort();
        Ok(out)
    }

    /// Writes a new version: `write` fills a temporary directory (the manifest last), which is
    /// synced and renamed into place, so the version appears complete or not at all. A crash
    /// leaves a dot-named temporary directory that nothing reads ([`Store::remove_debris`]).
    pub fn put_version(
        &self,
        category: &str,
        version: &str,
        write: impl FnOnce(&Path) -> std::result::Result<(), String>,
    ) -> Result<PathBuf> {
        let target = self.version_dir(category, version);
        let parent = target.parent().expect("a version directory has a parent").to_path_buf();
        fs::create_dir_all(&parent).map_err(io_err(&parent))?;
        let tmp = parent.join(format!(".{version}.{}.{}.tmp", std::process::id(), nanos()));
        let result = (|| {
            write(&tmp).map_err(|reason| StoreError::Corrupt { path: tmp.display().to_string(), reason })?;
            failpoint("save-version");
            for entry in fs::read_dir(&tmp).map_err(io_err(&tmp))? {
                let path = entry.map_err(io_err(&tmp))?.path();
                File::open(&path).and_then(|f| f.sync_all()).map_err(io_err(&path))?;
            }
            File::open(&tmp).and_then(|f| f.sync_all()).map_err(io_err(&tmp))?;
            fs::rename(&tmp, &target).map_err(io_err(&target))?;
            File::open(&parent).and_then(|f| f.sync_all()).map_err(io_err(&parent))
        })();
        if result.is_err() {
            let _ = fs::remove_dir_all(&tmp);
        }
        result.map(|()| target)
    }

    /// Removes the temporary directories a crash left behind in `category`'s versions.
    pub fn remove_debris(&self, category: &str) {
        let dir = self.category_dir(category).join("versions");
        for entry in fs::read_dir(&dir).into_iter().flatten().flatten() {
            let name = entry.file_name();
            if name.to_str().is_some_and(|n| n.starts_with('.') && n.ends_with(".tmp")) {
                tracing::info!("removing debris {}", entry.path().display());
                let _ = fs::remove_dir_all(entry.path());
            }
        }
    }

    /// Re-activates the active entry's `previous` version.
    pub fn rollback(&self, category: &str, actor: &str, reason: &str, expected_generation: Option<u64>) -> Result<u64> {
        let (generation, head) = self.head(category)?.ok_or_else(|| StoreError::NoPrevious(category.into()))?;
        let previous = head.previous.ok_or_else(|| StoreError::NoPrevious(category.into()))?;
        self.activate(category, &previous, actor, reason, Some(expected_generation.unwrap_or(generation)))
    }

    /// Imports the seed model directory `seed` for `category` (once: its id is content-derived)
    /// and activates it when the category has no activation yet, or when the active version
    /// is an older seed (the repository's model changed). Returns the seed's version id.
    pub fn import_seed(&self, category: &str, seed: &Path) -> Result<String> {
        let manifest_path = seed.join(MANIFEST);
        let manifest = fs::read(&manifest_path).map_err(io_err(&manifest_path))?;
        let digest: String = Sha256::digest(&manifest).iter().take(6).map(|b| format!("{b:02x}")).collect();
        let version = format!("seed-{digest}");
        let target = self.version_dir(category, &version);
        if !target.join(MANIFEST).is_file() {
            copy_version(seed, &target)?;
        }
        let replace = match self.head(category)? {
            None => true,
            Some((_, head)) => head.actor == SEED_ACTOR && head.version != version,
        };
        if replace {
            let reason = format!("imported seed {}", seed.display());
            match self.activate(category, &version, SEED_ACTOR, &reason, None) {
                Ok(_) | Err(StoreError::Conflict { .. }) => {} // another process imported it first
                Err(e) => return Err(e),
            }
        }
        Ok(version)
    }
}

fn activation_name(generation: u64) -> String {
    format!("{generation:020}.json")
}

/// Copies the files of a model directory into `target` atomically: into a temporary sibling,
/// every file synced, the manifest last, then renamed into place. Losing a race to another
/// importer of the same (content-named) version is fine.
fn copy_version(seed: &Path, target: &Path) -> Result<()> {
    let parent = target.parent().expect("a version directory has a parent");
    fs::create_dir_all(parent).map_err(io_err(parent))?;
    let name = target.file_name().and_then(|n| n.to_str()).unwrap_or("version");
    let tmp = parent.join(format!(".{name}.{}.{}.tmp", std::process::id(), nanos()));
    fs::create_dir(&tmp).map_err(io_err(&tmp))?;
    let result = (|| {
        let mut files: Vec<PathBuf> = fs::read_dir(seed)
            .map_err(io_err(seed))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file() && p.file_name().is_some_and(|n| n != MANIFEST))
            .collect();
        files.sort();
        files.push(seed.join(MANIFEST));
        for file in &files {
            let to = tmp.join(file.file_name().expect("a file has a name"));
            fs::copy(file, &to).map_err(io_err(file))?;
            File::open(&to).and_then(|f| f.sync_all()).map_err(io_err(&to))?;
        }
        File::open(&tmp).and_then(|f| f.sync_all()).map_err(io_err(&tmp))?;
        match fs::rename(&tmp, target) {
            Ok(()) => File::open(parent).and_then(|f| f.sync_all()).map_err(io_err(parent)),
            Err(_) if target.join(MANIFEST).is_file() => Ok(()),
            Err(e) => Err(io_err(target)(e)),
        }
    })();
    let _ = fs::remove_dir_all(&tmp);
    result
}

/// Writes `bytes` to `path` only if `path` does not exist: a synced temporary file hard-linked
/// into place (atomic and exclusive). Returns false when `path` already existed.
pub(crate) fn create_only(path: &Path, bytes: &[u8]) -> io::Result<bool> {
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let tmp = path.with_file_name(format!(".{name}.{}.{}.tmp", std::process::id(), nanos()));
    let result = (|| {
        let mut f = File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        match fs::hard_link(&tmp, path) {
            Ok(()) => {
                if let Some(parent) = path.parent() {
                    File::open(parent)?.sync_all()?;
                }
                Ok(true)
            }
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => Ok(false),
            Err(e) => Err(e),
        }
    })();
    let _ = fs::remove_file(&tmp);
    result
}

/// Crash-test hook: with `UDAPOSE_FAILPOINT=<name>` the process stops for good at the point of
/// that name (logged), so a test can `kill -9` it exactly there.
pub(crate) fn failpoint(name: &str) {
    if std::env::var("UDAPOSE_FAILPOINT").is_ok_and(|v| v == name) {
        tracing::warn!("failpoint {name}: stopped here");
        loop {
            std::thread::sleep(std::time::Duration::from_secs(3600));
        }
    }
}

pub(crate) fn nanos() -> u128 {
    SystemTime::now().duration_since(UNIX_EPOCH).map_or(0, |d| d.as_nanos())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("udapose-store-{name}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&dir);
        dir
    }

    fn shipped() -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../models/car")
    }

    #[test]
    fn category_names_cannot_escape_the_store() {
        for good in ["car", "bus-2", "a_b", "0"] {
            assert!(valid_category(good), "{good}");
        }
        for bad in ["", "..", "../etc", "car/../x", "Car", "-car", "car.json", "a b", &"x".repeat(65)] {
            assert!(!valid_category(bad), "{bad:?}");
        }
    }

    #[test]
    fn a_seed_is_imported_once_and_activated_as_generation_zero() {
        let root = temp("seed");
        let store = Store::open(&root).unwrap();
        let version = store.import_seed("car", &shipped()).unwrap();
        assert!(version.starts_with("seed-") && version.len() == 17, "{version}");
        assert_eq!(store.import_seed("car", &shipped()).unwrap(), version);
        let (generation, head) = store.head("car").unwrap().unwrap();
        assert_eq!(
            (generation, head.version.as_str(), head.previous, head.actor.as_str()),
            (0, &*version, None, "seed")
        );
        assert_eq!(store.manifest("car", &version).unwrap().crop, [128, 320]);
        assert_eq!(store.categories().unwrap(), ["car"]);
        assert!(root.join("models/car/activations/00000000000000000000.json").is_file());
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn activation_is_create_only_and_checks_the_expected_generation() {
        let root = temp("activate");
        let store = Store::open(&root).unwrap();
        let seed = store.import_seed("car", &shipped()).unwrap();
        // A second version (same files, another name) to switch between.
        copy_version(&shipped(), &store.version_dir("car", "v2")).unwrap();
        assert_eq!(store.activate("car", "v2", "test", "try", Some(0)).unwrap(), 1);
        let err = store.activate("car", &seed, "test", "stale", Some(0)).unwrap_err();
        assert!(matches!(err, StoreError::Conflict { expected: 0, found: 1, .. }), "{err}");
        assert!(matches!(store.activate("car", "nope", "t", "r", None), Err(StoreError::UnknownVersion { .. })));
        assert_eq!(store.rollback("car", "test", "back", None).unwrap(), 2);
        let (generation, head) = store.head("car").unwrap().unwrap();
        assert_eq!((generation, head.version, head.previous.as_deref()), (2, seed.clone(), Some("v2")));
        // A restart does not re-activate the seed over a newer activation... unless it is a seed.
        store.import_seed("car", &shipped()).unwrap();
        assert_eq!(store.head("car").unwrap().unwrap().0, 2);
        // create_only never overwrites.
        let path = root.join("x.json");
        assert!(create_only(&path, b"1").unwrap());
        assert!(!create_only(&path, b"2").unwrap());
        assert_eq!(fs::read(&path).unwrap(), b"1");
        fs::remove_dir_all(&root).unwrap();
    }
}
