//! Stages resumed from their round snapshots (`udapose-lab adapt`/`finetune` rerun after an
//! interruption): their time counts every process, and the report names them, because a resumed
//! run restarts Adam's moments and so is not bit-identical to an uninterrupted one.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::Value;
use udapose_engine::checkpoint::MANIFEST;

/// A model's `training.run` record, if it was resumed.
fn resumed_run(model: &Path) -> Option<Value> {
    let text = std::fs::read_to_string(model.join(MANIFEST)).ok()?;
    let run = serde_json::from_str::<Value>(&text).ok()?["training"]["run"].take();
    run["resumed_after"].as_u64().map(|_| run)
}

/// A resumed model stage's seconds over all its processes (the manifest's `training.run.seconds`),
/// where the last process's wall time would undercount.
pub(super) fn seconds(model: &Path) -> Option<f64> {
    resumed_run(model)?["seconds"].as_f64()
}

/// The report's resumed model stages among its `outputs`, `<variant>/<domain>` (relative to
/// `work`) → rounds restored.
pub(super) fn stages(work: &Path, outputs: &[PathBuf]) -> BTreeMap<String, u64> {
    let models = outputs.iter().filter(|o| o.ends_with(MANIFEST)).filter_map(|o| o.parent());
    let resumed = |model: &Path| {
        let rounds = resumed_run(model)?["resumed_after"].as_u64()?;
        Some((model.strip_prefix(work).ok()?.to_string_lossy().into_owned(), rounds))
    };
    models.filter_map(resumed).collect()
}

/// The report's note on them; empty when no stage was resumed.
pub(super) fn markdown(stages: &BTreeMap<String, u64>) -> String {
    if stages.is_empty() {
        return String::new();
    }
    let list: Vec<String> = stages.iter().map(|(s, r)| format!("`{s}` after round {r}")).collect();
    format!(
        "\nResumed from round snapshots (Adam's moments restart there, so these differ slightly from an \
         uninterrupted run): {}.\n",
        list.join(", ")
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_resumed_models_are_named() {
        let work = std::env::temp_dir().join(format!("udapose-resumed-{}", std::process::id()));
        let mut outputs = Vec::new();
        for (model, run) in [
            ("strong_oracle/combined", r#"{"resumed_after": 2, "seconds": 90.5}"#),
            ("adapted/combined", r#"{"resumed_after": null, "seconds": 10.0}"#),
            ("adapted/source", r#"{"seconds": 5.0}"#),
        ] {
            std::fs::create_dir_all(work.join(model)).unwrap();
            let manifest = format!(r#"{{"training": {{"run": {run}}}}}"#);
            std::fs::write(work.join(model).join(MANIFEST), manifest).unwrap();
            outputs.push(work.join(model).join(MANIFEST));
        }
        outputs.push(work.join("eval/strong_oracle/combined.json"));
        let found = stages(&work, &outputs);
        assert_eq!(found, BTreeMap::from([("strong_oracle/combined".to_string(), 2)]));
        assert_eq!(seconds(&work.join("strong_oracle/combined")), Some(90.5));
        assert_eq!(seconds(&work.join("adapted/combined")), None);
        assert!(markdown(&found).contains("`strong_oracle/combined` after round 2"));
        assert!(markdown(&BTreeMap::new()).is_empty());
        std::fs::remove_dir_all(&work).unwrap();
    }
}
