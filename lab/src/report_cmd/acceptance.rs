//! The report's acceptance section: what the issue that asked for the report checks. Cars answer
//! the adaptation issue (EM gains, gaps closed, the cost in-domain); the other categories answer
//! the categories issue (gap closed against the strong oracle on `combined` and the corruptions).
//! Each gap-closed line says whether it is met.

use serde_json::{Map, Value};
use udapose_lab::assets::category::Category;

use super::stats::f;
use super::{ABLATION, MIN_GAP, strong_domains};

/// The categories issue's target: share of the gap to the strong oracle closed.
const CATEGORY_GAP: f64 = 0.6;

/// Of the 5 corruptions, how many must reach [`CATEGORY_GAP`].
const CATEGORY_CORRUPTIONS: usize = 3;

/// A domain with no gap to close passes where adaptation costs it at most this (BENCHMARK.md §6).
const NA_TOLERANCE: f64 = 0.02;

pub(super) fn markdown(category: Category, domains: &Map<String, Value>) -> String {
    let entry = |d: &str| domains.get(d).cloned().unwrap_or(Value::Null);
    match category {
        Category::Car => adaptation(&entry),
        _ => categories(&entry),
    }
}

fn corruptions() -> impl Iterator<Item = &'static str> {
    ABLATION.iter().copied().filter(|d| d.starts_with("corrupt/"))
}

/// The adaptation issue's checks: EM gains with their intervals, gaps closed against the strong
/// oracle, the cost of adapting in-domain.
fn adaptation(entry: &dyn Fn(&str) -> Value) -> String {
    let mut md = String::from("\n## Acceptance\n\n");
    for d in ["combined", "occ-l1"] {
        md.push_str(&format!("- EM gain on {d}: {} (target: interval above 0)\n", em_text(&entry(d))));
    }
    let em_above_zero = |d: &str| entry(d)["em_gain_ci"][0].as_f64().is_some_and(|lo| lo > 0.0);
    let passed = corruptions().filter(|d| em_above_zero(d)).count();
    md.push_str(&format!("- EM gain above 0 on {passed} of the {} corruptions (target ≥ 3):", corruptions().count()));
    for d in corruptions() {
        md.push_str(&format!(" {d} {};", em_text(&entry(d))));
    }
    md.push('\n');
    for d in strong_domains().into_iter().filter(|d| *d != "occ-l1").chain(["occ-l1"]) {
        let target = if ["shape", "pose", "occ-l1"].contains(&d) { 0.5 } else { 0.7 };
        md.push_str(&format!("- {d}: {}\n", gap_line(&entry(d), target)));
    }
    let acc = |v: &str| entry("source")[v]["acc_pi_6"].as_f64();
    if let (Some(s), Some(a)) = (acc("source"), acc("adapted")) {
        md.push_str(&format!("- source: adapting on source costs {:+.3} Acc@π/6 (target ≥ −0.01)\n", a - s));
    }
    md
}

/// The categories issue's check: 3DUDA closes ≥ 0.6 of the gap to the strong oracle on
/// `combined` and on at least 3 of the 5 corruptions.
fn categories(entry: &dyn Fn(&str) -> Value) -> String {
    let mut md = String::from("\n## Acceptance (the categories issue)\n\n");
    md.push_str(&format!("- combined: {}\n", gap_line(&entry("combined"), CATEGORY_GAP)));
    let results: Vec<Option<bool>> = corruptions().map(|d| gap_passes(&entry(d), CATEGORY_GAP)).collect();
    let passed = results.iter().filter(|r| **r == Some(true)).count();
    let pending = results.iter().filter(|r| r.is_none()).count();
    // Undecided while the corruptions still to run could make up the count.
    let decided = (passed >= CATEGORY_CORRUPTIONS || passed + pending < CATEGORY_CORRUPTIONS)
        .then_some(passed >= CATEGORY_CORRUPTIONS);
    md.push_str(&format!(
        "- {passed} of the {} corruptions pass (target ≥ {CATEGORY_CORRUPTIONS}): {}\n",
        results.len(),
        verdict(decided)
    ));
    for d in corruptions() {
        md.push_str(&format!("  - {d}: {}\n", gap_line(&entry(d), CATEGORY_GAP)));
    }
    md
}

/// `gap closed against the strong oracle 0.72 [0.55, 0.90] (target ≥ 0.7): met`.
fn gap_line(e: &Value, target: f64) -> String {
    format!(
        "gap closed against the strong oracle {} (target ≥ {target}): {}",
        gap_text(e),
        verdict(gap_passes(e, target))
    )
}

fn verdict(passes: Option<bool>) -> &'static str {
    match passes {
        Some(true) => "met",
        Some(false) => "not met",
        None => "not run yet",
    }
}

/// Whether a domain meets a gap-closed target (BENCHMARK.md §6): on the point estimate; where
/// gap closed is n/a (the strong oracle gains under [`MIN_GAP`], or the source scores too high
/// for it to run), where adapted ≥ source − [`NA_TOLERANCE`]. None before its stages ran.
fn gap_passes(e: &Value, target: f64) -> Option<bool> {
    if let Some(g) = e["gap_closed_strong"].as_f64() {
        return Some(g >= target);
    }
    let (source, adapted) = (e["source"]["acc_pi_6"].as_f64()?, e["adapted"]["acc_pi_6"].as_f64()?);
    let no_gap = e["strong_oracle"].is_object() || source >= 1.0 - MIN_GAP;
    no_gap.then_some(adapted >= source - NA_TOLERANCE)
}

/// `+0.012 [−0.010, +0.030]`, or "not run yet".
fn em_text(e: &Value) -> String {
    match (e["em_gain"].as_f64(), e["em_gain_ci"][0].as_f64(), e["em_gain_ci"][1].as_f64()) {
        (Some(x), Some(lo), Some(hi)) => format!("{x:+.3} [{lo:+.3}, {hi:+.3}]"),
        _ => "not run yet".into(),
    }
}

/// `0.72 [0.55, 0.90]`, "n/a" (oracle − source below [`MIN_GAP`]) or "not run yet".
fn gap_text(e: &Value) -> String {
    match (
        e["gap_closed_strong"].as_f64(),
        e["gap_closed_strong_ci"][0].as_f64(),
        e["gap_closed_strong_ci"][1].as_f64(),
    ) {
        (Some(x), Some(lo), Some(hi)) => format!("{x:.2} [{lo:.2}, {hi:.2}]"),
        (Some(x), ..) => format!("{x:.2}"),
        _ if e["strong_oracle"].is_object() => {
            let d = f(&e["strong_oracle"]["acc_pi_6"]) - f(&e["source"]["acc_pi_6"]);
            format!("n/a (strong oracle − source {d:+.3} < {MIN_GAP})")
        }
        _ if f(&e["source"]["acc_pi_6"]) >= 1.0 - MIN_GAP => {
            format!("n/a (source {:.3}: no gap of {MIN_GAP} to close; not run)", f(&e["source"]["acc_pi_6"]))
        }
        _ => "not run yet".into(),
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    fn domains(gaps: &[(&str, f64)]) -> Map<String, Value> {
        gaps.iter()
            .map(|(d, g)| (d.to_string(), json!({"gap_closed_strong": g, "gap_closed_strong_ci": [g - 0.2, g + 0.2]})))
            .collect()
    }

    /// A domain with no gap to close: the strong oracle `strong` (None: not run), source and
    /// adapted accuracies.
    fn no_gap(strong: Option<f64>, source: f64, adapted: f64) -> Value {
        let mut e = json!({"source": {"acc_pi_6": source}, "adapted": {"acc_pi_6": adapted}});
        if let Some(s) = strong {
            e["strong_oracle"] = json!({"acc_pi_6": s});
        }
        e
    }

    fn chair(fog_adapted: f64) -> String {
        let mut d = domains(&[
            ("combined", 0.65),
            ("corrupt/gaussian_noise", 0.61),
            ("corrupt/glass_blur", 0.59),
            ("corrupt/speckle_noise", 0.9),
        ]);
        d.insert("corrupt/fog".into(), no_gap(Some(0.82), 0.80, fog_adapted));
        d.insert("corrupt/contrast".into(), no_gap(None, 0.97, 0.94));
        markdown(Category::Chair, &d)
    }

    #[test]
    fn a_category_counts_the_corruptions_that_pass() {
        let md = chair(0.785);
        assert!(
            md.contains("- combined: gap closed against the strong oracle 0.65 [0.45, 0.85] (target ≥ 0.6): met"),
            "{md}"
        );
        assert!(md.contains("- 3 of the 5 corruptions pass (target ≥ 3): met"), "{md}");
        assert!(
            md.contains(
                "  - corrupt/glass_blur: gap closed against the strong oracle 0.59 [0.39, 0.79] (target ≥ 0.6): \
                 not met"
            ),
            "{md}"
        );
        let fog = "corrupt/fog: gap closed against the strong oracle n/a (strong oracle − source +0.020 < 0.05)";
        assert!(md.contains(&format!("{fog} (target ≥ 0.6): met")), "{md}");
        let contrast = "corrupt/contrast: gap closed against the strong oracle n/a (source 0.970: no gap of 0.05 to \
                        close; not run)";
        assert!(md.contains(&format!("{contrast} (target ≥ 0.6): not met")), "{md}");
        assert!(!md.contains("EM gain"), "cars' checks stay cars': {md}");
    }

    #[test]
    fn a_domain_with_no_gap_passes_only_where_adapting_costs_at_most_two_points() {
        let md = chair(0.775);
        assert!(md.contains("- 2 of the 5 corruptions pass (target ≥ 3): not met"), "{md}");
        assert!(md.contains("< 0.05) (target ≥ 0.6): not met"), "{md}");
    }

    #[test]
    fn a_domain_whose_stages_have_not_run_is_not_counted() {
        let md = markdown(Category::Bus, &domains(&[("corrupt/fog", 0.9)]));
        assert!(
            md.contains("- combined: gap closed against the strong oracle not run yet (target ≥ 0.6): not run yet"),
            "{md}"
        );
        assert!(md.contains("- 1 of the 5 corruptions pass (target ≥ 3): not run yet"), "{md}");
        let mut failing =
            domains(&[("corrupt/gaussian_noise", 0.1), ("corrupt/glass_blur", 0.2), ("corrupt/fog", 0.3)]);
        failing.insert("corrupt/contrast".into(), json!({}));
        let md = markdown(Category::Bus, &failing);
        assert!(
            md.contains("- 0 of the 5 corruptions pass (target ≥ 3): not met"),
            "2 still to run cannot make 3: {md}"
        );
    }

    #[test]
    fn cars_answer_the_adaptation_issue() {
        let mut d = domains(&[("combined", 0.8)]);
        d["combined"]["em_gain"] = json!(0.02);
        d["combined"]["em_gain_ci"] = json!([0.005, 0.04]);
        let md = markdown(Category::Car, &d);
        assert!(md.contains("- EM gain on combined: +0.020 [+0.005, +0.040] (target: interval above 0)"), "{md}");
        assert!(
            md.contains("- combined: gap closed against the strong oracle 0.80 [0.60, 1.00] (target ≥ 0.7): met"),
            "{md}"
        );
        assert!(
            md.contains("- shape: gap closed against the strong oracle not run yet (target ≥ 0.5): not run yet"),
            "{md}"
        );
    }
}
