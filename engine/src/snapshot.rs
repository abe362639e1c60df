//! A long run's resumable state on disk: one directory per point of the run (an epoch, a round)
//! holding its tensors (`state.safetensors`) and a JSON record (`progress.json`, written last).
//! Each is built under a temporary name and renamed into place, so a resumed run sees a whole
//! snapshot or none; the newest few of a work directory are kept. Source training and the
//! adaptation's rounds both use it (the house keeps at most 15 minutes of work at risk).

use std::collections::BTreeMap;
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::Serialize;
use serde::de::DeserializeOwned;
use tch::Tensor;

use crate::error::{CheckpointError, EngineError, Result};

const STATE: &str = "state.safetensors";
const RECORD: &str = "progress.json";

pub(crate) fn format_error(dir: &Path, what: impl std::fmt::Display) -> EngineError {
    CheckpointError::Format { path: dir.display().to_string(), reason: what.to_string() }.into()
}

/// Writes `tensors` and `record` to `<work>/<name>/` through a temporary directory, synced,
/// replacing an older snapshot of that name.
pub(crate) fn write(work: &Path, name: &str, tensors: &[(String, Tensor)], record: &impl Serialize) -> Result<()> {
    fs::create_dir_all(work)?;
    let dir = work.join(name);
    let tmp = work.join(format!(".{name}.tmp"));
    let _ = fs::remove_dir_all(&tmp);
    fs::create_dir_all(&tmp)?;
    Tensor::write_safetensors(tensors, tmp.join(STATE)).map_err(|e| format_error(&tmp, e))?;
    File::open(tmp.join(STATE))?.sync_all()?;
    let mut f = File::create(tmp.join(RECORD))?;
    f.write_all(serde_json::to_string(record).map_err(|e| format_error(&tmp, e))?.as_bytes())?;
    f.sync_all()?;
    File::open(&tmp)?.sync_all()?;
    let _ = fs::remove_dir_all(&dir);
    fs::rename(&tmp, &dir)?;
    File::open(work)?.sync_all()?;
    Ok(())
}

/// The complete snapshots of `work` whose names `parse` reads, oldest first.
pub(crate) fn complete<K: Ord>(work: &Path, parse: impl Fn(&str) -> Option<K>) -> Result<Vec<(K, PathBuf)>> {
    if !work.is_dir() {
        return Ok(Vec::new());
    }
    let mut found: Vec<(K, PathBuf)> = fs::read_dir(work)?
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let at = parse(e.file_name().to_str()?)?;
            e.path().join(RECORD).is_file().then(|| (at, e.path()))
        })
        .collect();
    found.sort_by(|a, b| a.0.cmp(&b.0));
    Ok(found)
}

/// Removes all but the `keep` newest complete snapshots.
pub(crate) fn prune<K: Ord>(work: &Path, parse: impl Fn(&str) -> Option<K>, keep: usize) -> Result<()> {
    for (_, p) in complete(work, parse)?.iter().rev().skip(keep) {
        fs::remove_dir_all(p)?;
    }
    Ok(())
}

/// A snapshot's record and tensors.
pub(crate) fn read<T: DeserializeOwned>(dir: &Path) -> Result<(T, BTreeMap<String, Tensor>)> {
    let text = fs::read_to_string(dir.join(RECORD))?;
    let record = serde_json::from_str(&text).map_err(|e| format_error(dir, e))?;
    Ok((record, crate::checkpoint::read_tensors(&dir.join(STATE))?))
}

/// The tensor `name` of a snapshot read from `dir`.
pub(crate) fn get<'t>(dir: &Path, tensors: &'t BTreeMap<String, Tensor>, name: &str) -> Result<&'t Tensor> {
    tensors.get(name).ok_or_else(|| format_error(dir, format!("no {name}")))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The newest complete snapshot wins; an unfinished (no record) or temporary directory
    /// never counts, and pruning keeps the newest.
    #[test]
    fn only_complete_snapshots_count_and_the_newest_are_kept() {
        let work = std::env::temp_dir().join(format!("udapose-snapshot-{}", std::process::id()));
        let parse = |n: &str| n.strip_prefix("round-")?.parse::<usize>().ok();
        for r in 1..=3 {
            write(&work, &format!("round-{r}"), &[("x".into(), Tensor::from(r as f32))], &r).unwrap();
        }
        fs::create_dir_all(work.join("round-4")).unwrap();
        fs::create_dir_all(work.join(".round-5.tmp")).unwrap();
        let found: Vec<usize> = complete(&work, parse).unwrap().into_iter().map(|(k, _)| k).collect();
        assert_eq!(found, [1, 2, 3]);
        prune(&work, parse, 2).unwrap();
        let (record, tensors): (usize, _) = read(&work.join("round-3")).unwrap();
        assert_eq!(record, 3);
        assert_eq!(f32::try_from(get(&work, &tensors, "x").unwrap()).unwrap(), 3.0);
        assert!(!work.join("round-1").exists() && work.join("round-2").exists());
        assert!(get(&work, &tensors, "y").is_err());
        fs::remove_dir_all(&work).unwrap();
    }
}
