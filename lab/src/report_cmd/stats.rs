//! The report's numbers from the evaluations' per-image errors: Acc@π/6 hits, gaps closed and
//! gains with paired bootstrap intervals, the schema's `M`.

use std::path::Path;

use serde_json::Value;
use udapose_engine::metrics::paired_bootstrap;

use super::MIN_GAP;

pub(super) fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

pub(super) fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

pub(super) fn mean_of(v: &Value) -> Option<f64> {
    let x: Vec<f64> = v.as_array()?.iter().filter_map(Value::as_f64).collect();
    (!x.is_empty()).then(|| mean(&x))
}

/// `M` of the report schema with its intervals (the per-image arrays stay in the eval files).
pub(super) fn metrics(e: &Option<Value>) -> Value {
    let Some(e) = e else { return Value::Null };
    let keys = ["acc_pi_6", "acc_pi_18", "med_err_deg", "n", "acc_pi_6_ci", "acc_pi_18_ci", "med_err_deg_ci"];
    Value::Object(keys.iter().map(|k| (k.to_string(), e[*k].clone())).collect())
}

/// The source model's version, from its manifest.
pub(super) fn model_version(dir: &Path) -> Value {
    let manifest = std::fs::read_to_string(dir.join("manifest.json")).ok();
    manifest.and_then(|m| serde_json::from_str::<Value>(&m).ok()).map_or(Value::Null, |m| m["version"].clone())
}

/// Per test image, whether its error is under π/6 (Acc@π/6's hits).
fn hits(e: &Value) -> Vec<bool> {
    e["errors_deg"]
        .as_array()
        .map(|x| x.iter().map(|v| v.as_f64().unwrap_or(180.0) < 30.0).collect())
        .unwrap_or_default()
}

fn share(h: &[bool], idx: &[usize]) -> f64 {
    idx.iter().filter(|&&i| h[i]).count() as f64 / idx.len() as f64
}

/// Gap closed on Acc@π/6 and its paired bootstrap interval (the same resampled images for the
/// three models; 1000 resamples, seed 0). None where oracle − source < [`MIN_GAP`].
pub(super) fn gap_closed(s: &Value, a: &Value, o: &Value) -> (Option<f64>, Option<[f64; 2]>) {
    let (hs, ha, ho) = (hits(s), hits(a), hits(o));
    let n = hs.len();
    if n == 0 || ha.len() != n || ho.len() != n {
        return (None, None);
    }
    let all: Vec<usize> = (0..n).collect();
    let (s0, a0, o0) = (share(&hs, &all), share(&ha, &all), share(&ho, &all));
    if o0 - s0 < MIN_GAP {
        return (None, None);
    }
    let ci = paired_bootstrap(n, 1000, 0, |idx| {
        let (s, a, o) = (share(&hs, idx), share(&ha, idx), share(&ho, idx));
        (o - s > 0.0).then(|| (a - s) / (o - s))
    });
    (Some((a0 - s0) / (o0 - s0)), ci)
}

/// `to − from` on Acc@π/6 with its paired bootstrap interval (same images; 1000 resamples,
/// seed 0): e.g. the EM gain, adapted − BN only.
pub(super) fn gain(from: &Option<Value>, to: &Option<Value>) -> (Option<f64>, Option<[f64; 2]>) {
    let (Some(from), Some(to)) = (from, to) else { return (None, None) };
    let (hf, ht) = (hits(from), hits(to));
    let n = hf.len();
    if n == 0 || ht.len() != n {
        return (None, None);
    }
    let all: Vec<usize> = (0..n).collect();
    let ci = paired_bootstrap(n, 1000, 0, |idx| Some(share(&ht, idx) - share(&hf, idx)));
    (Some(share(&ht, &all) - share(&hf, &all)), ci)
}
