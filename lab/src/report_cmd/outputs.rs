//! A report's stage outputs: the JSON files its stages wrote in the work folder, a model's
//! `<variant>/<domain>/manifest.json` and an evaluation's `eval/<variant>/<domain>.json`. The
//! commits they ran at and the stages that resumed are both read off this one listing.

use std::path::{Path, PathBuf};

/// The JSON files in `work`, three levels deep at most, sorted. Round snapshots (hidden folders)
/// are not outputs.
pub(super) fn list(work: &Path) -> Vec<PathBuf> {
    let mut found = Vec::new();
    walk(work, 3, &mut found);
    found.sort();
    found
}

fn walk(dir: &Path, depth: usize, found: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else { return };
    for path in entries.filter_map(|e| Some(e.ok()?.path())) {
        if path.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.')) {
            continue;
        }
        if path.is_dir() && depth > 1 {
            walk(&path, depth - 1, found);
        } else if path.extension().is_some_and(|e| e == "json") {
            found.push(path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lists_models_and_evaluations_but_not_snapshots() {
        let work = std::env::temp_dir().join(format!("udapose-report-outputs-{}", std::process::id()));
        for rel in [
            "adapted/combined/manifest.json",
            "adapted/.combined.rounds/round-0001/manifest.json",
            "eval/adapted/combined.json",
            "eval/adapted/combined.txt",
            "timings.json",
        ] {
            let file = work.join(rel);
            std::fs::create_dir_all(file.parent().unwrap()).unwrap();
            std::fs::write(file, "{}").unwrap();
        }
        let found = list(&work);
        std::fs::remove_dir_all(&work).unwrap();
        let rel: Vec<_> = found.iter().map(|p| p.strip_prefix(&work).unwrap().to_str().unwrap().to_owned()).collect();
        assert_eq!(rel, ["adapted/combined/manifest.json", "eval/adapted/combined.json", "timings.json"]);
    }
}
