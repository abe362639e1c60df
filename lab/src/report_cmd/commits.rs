//! The builds a report's stages ran at. A report resumes over sessions and `--no-run` rewrites it
//! with whatever build is at hand, so the commit of the binary that wrote it says little about the
//! numbers; every stage's output names its own (a model's `training.commit`, an evaluation's
//! `commit`), and the report counts them.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::Value;

/// Stage outputs per commit; an output that names none (`timings.json`) is not counted.
pub(super) fn stages(outputs: &[PathBuf]) -> BTreeMap<String, usize> {
    let mut found = BTreeMap::new();
    for commit in outputs.iter().filter_map(|o| commit(o)) {
        *found.entry(commit).or_default() += 1;
    }
    found
}

fn commit(file: &Path) -> Option<String> {
    let v: Value = serde_json::from_str(&std::fs::read_to_string(file).ok()?).ok()?;
    let c = v["commit"].as_str().or(v["training"]["commit"].as_str())?;
    Some(c.to_string())
}

/// `` `1e3eced` (169 outputs), `e837459` (10) ``, most used first; "none found" when empty.
pub(super) fn markdown(stages: &BTreeMap<String, usize>) -> String {
    let mut by_use: Vec<(&String, &usize)> = stages.iter().collect();
    by_use.sort_by(|a, b| b.1.cmp(a.1).then(a.0.cmp(b.0)));
    let list: Vec<String> = by_use
        .iter()
        .enumerate()
        .map(|(i, (c, n))| if i == 0 { format!("`{c}` ({n} outputs)") } else { format!("`{c}` ({n})") })
        .collect();
    if list.is_empty() { "none found".into() } else { list.join(", ") }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_the_commits_outputs_name() {
        let work = std::env::temp_dir().join(format!("udapose-report-commits-{}", std::process::id()));
        let write = |rel: &str, text: &str| {
            let file = work.join(rel);
            std::fs::create_dir_all(file.parent().unwrap()).unwrap();
            std::fs::write(&file, text).unwrap();
            file
        };
        let outputs = [
            write("adapted/combined/manifest.json", r#"{"training": {"commit": "aaa"}}"#),
            write("eval/adapted/combined.json", r#"{"commit": "aaa"}"#),
            write("eval/source/combined.json", r#"{"commit": "bbb"}"#),
            write("timings.json", r#"{"adapt combined": 12.0}"#),
        ];
        let found = stages(&outputs);
        std::fs::remove_dir_all(&work).unwrap();
        assert_eq!(found, BTreeMap::from([("aaa".into(), 2), ("bbb".into(), 1)]));
        assert_eq!(markdown(&found), "`aaa` (2 outputs), `bbb` (1)");
    }
}
