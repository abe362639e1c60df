//! The gate benchmark's report: the `margin_gain` sweep, the per-domain decisions against the
//! true accuracy changes, and the JSON and Markdown.

use anyhow::Result;
use serde_json::{Value, json};
use udapose_engine::gate::{Decision, GateConfig, Measured};
use udapose_engine::pose_error;
use udapose_lab::atomic::write_atomic;

use super::{DomainResult, GateArgs, agrees, angles};
use crate::harness::{git_commit, machine};

/// One `margin_gain` of the sweep: its agreement with the sign of the adapt split's change and,
/// for comparison, with the (noisier) held-out images' change, each as (agree, counted).
struct SweepRow {
    gain: f64,
    adapt: (usize, usize),
    held_out: (usize, usize),
}

/// The `margin_gain` of `gains` whose decisions agree best with the sign of the adapt split's
/// accuracy change, ties to the smallest positive value (a candidate must *raise* its margin:
/// with 0, a no-op adaptation that changed nothing would pass), else the smallest; with each
/// value's agreement counts.
fn choose_gain(results: &[DomainResult], base: &GateConfig, gains: &[f64]) -> Result<(f64, Vec<SweepRow>)> {
    let mut sweep = Vec::with_capacity(gains.len());
    for &gain in gains {
        let config = GateConfig { margin_gain: gain, ..base.clone() };
        let mut row = SweepRow { gain, adapt: (0, 0), held_out: (0, 0) };
        for r in results {
            let passed = r.decide(&config)?.passed;
            let (s, a, _) = r.adapt_split;
            let (hs, ha) = r.adapt_accuracy()?;
            for (change, (agree, counted)) in [(a - s, &mut row.adapt), (ha - hs, &mut row.held_out)] {
                if let Some(ok) = agrees(passed, change) {
                    *counted += 1;
                    *agree += usize::from(ok);
                }
            }
        }
        sweep.push(row);
    }
    let best = sweep.iter().map(|s| s.adapt.0).max().unwrap_or(0);
    let tied: Vec<f64> = sweep.iter().filter(|s| s.adapt.0 == best).map(|s| s.gain).collect();
    let smallest = |v: &[f64]| v.iter().copied().fold(f64::INFINITY, f64::min);
    let positive: Vec<f64> = tied.iter().copied().filter(|&g| g > 0.0).collect();
    let chosen = if positive.is_empty() { smallest(&tied) } else { smallest(&positive) };
    Ok((chosen, sweep))
}

fn fmt_agree(v: Option<bool>) -> &'static str {
    match v {
        Some(true) => "yes",
        Some(false) => "**no**",
        None => "n/a (no change)",
    }
}

/// Whether the candidates were adapted on the held-out images too (by their manifests' image
/// counts), as a sentence for the report.
fn trained_on(results: &[DomainResult]) -> String {
    let whole = results.iter().all(|r| r.trained_on == Some(r.adapt_split.2 as u64));
    let without = results.iter().all(|r| r.trained_on == Some((r.adapt_split.2 - r.images.len()) as u64));
    if whole && !without {
        "The candidates were adapted on the whole adapt split, held-out images included (a service job never \
         trains on the held-out bucket)."
            .into()
    } else if without && !whole {
        "The candidates were adapted on the adapt split without the held-out bucket, as a service job is.".into()
    } else {
        let counts: Vec<String> = results
            .iter()
            .map(|r| format!("{} {}", r.domain, r.trained_on.map_or("?".into(), |n| n.to_string())))
            .collect();
        format!("Images each candidate was adapted on (its manifest): {}.", counts.join(", "))
    }
}

/// How many decisions agree with the accuracy changes, over every domain.
#[derive(Default)]
struct Totals {
    passed: usize,
    agree_test: usize,
    counted_test: usize,
    agree_adapt: usize,
    counted_adapt: usize,
    agree_significant: usize,
    counted_significant: usize,
}

pub(super) fn write_report(args: &GateArgs, config: &GateConfig, results: &[DomainResult], seconds: f64) -> Result<()> {
    let (chosen, sweep) = choose_gain(results, config, &args.gains)?;
    let command =
        ["udapose-bench".to_string()].into_iter().chain(std::env::args().skip(1)).collect::<Vec<_>>().join(" ");
    let commit = git_commit();
    let mut md = header_markdown(args, config, results, seconds, &command, &commit);
    let mut domains = serde_json::Map::new();
    let mut totals = Totals::default();
    for r in results {
        let (row, value) = domain_report(r, config, &mut totals)?;
        md.push_str(&row);
        domains.insert(r.domain.clone(), value);
    }
    let Totals { passed, agree_test, counted_test, agree_adapt, counted_adapt, agree_significant, counted_significant } =
        totals;
    md.push_str(&format!(
        "\n**Totals**: {passed} of {} candidates pass. Decisions agree with the sign of the test-split change in \
         **{agree_test} of {counted_test}** domains; in **{agree_significant} of {counted_significant}** of those whose \
         test change is beyond noise (McNemar |z| ≥ 1.96: z = (gained − lost)/√(gained + lost), images only one model \
         gets within π/6); and with the sign of the adapt-split change in {agree_adapt} of {counted_adapt} (domains \
         whose accuracy did not change are not counted).\n\n",
        results.len()
    ));
    md.push_str(&sweep_markdown(results, config, chosen, &sweep));
    let mut report = json!({
        "command": command,
        "commit": commit,
        "machine": machine(),
        "seconds": seconds,
        "note": args.note,
        "source": args.source.display().to_string(),
        "adapted": args.adapted.display().to_string(),
        "data": args.data.display().to_string(),
        "images": if args.all_adapt { "adapt" } else { "held-out adapt" },
        "config": config,
        "totals": {
            "domains": results.len(),
            "passed": passed,
            "agree_test": agree_test, "counted_test": counted_test,
            "agree_adapt": agree_adapt, "counted_adapt": counted_adapt,
            "agree_test_significant": agree_significant, "counted_test_significant": counted_significant,
        },
        "margin_gain_sweep": sweep.iter().map(|r| json!({
            "margin_gain": r.gain,
            "agree_adapt_split": r.adapt.0, "counted_adapt_split": r.adapt.1,
            "agree_held_out": r.held_out.0, "counted_held_out": r.held_out.1,
        })).collect::<Vec<_>>(),
        "margin_gain_chosen": chosen,
    });
    report["domains"] = Value::Object(domains);
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    write_atomic(&args.out.with_extension("md"), md.as_bytes())?;
    eprintln!(
        "{passed}/{} pass; agree with test Δ in {agree_test}/{counted_test} ({agree_significant}/{counted_significant} \
         significant), adapt Δ in {agree_adapt}/{counted_adapt}; margin_gain chosen on adapt: {chosen}",
        results.len()
    );
    Ok(())
}

/// The Markdown's title, setting and the head of the per-domain table.
fn header_markdown(
    args: &GateArgs,
    config: &GateConfig,
    results: &[DomainResult],
    seconds: f64,
    command: &str,
    commit: &str,
) -> String {
    let bucket = if args.all_adapt { "every adapt-split image" } else { "the held-out adapt-split images" };
    let trained = trained_on(results);
    let mut md = format!(
        "# Validation gate: decisions vs. the true accuracy change\n\n\
         `{command}` (commit `{commit}`, {}, {:.0} s).\n\n\
         Active model: `{}` (source). Candidate: each domain's 3DUDA-adapted model under `{}`. The gate measures both on \
         {bucket} of the domain (sha256 of the file bytes in `gate::held_out`, the service's rule), without labels, \
         and decides with `margin_gain = {}`, `flip_se = {}`, `entropy_drop = {}`, `entropy_floor = {}`. With the labels, \
         the change of Acc@π/6 (adapted − source) on the same images (Δ held-out), on the whole adapt split \
         (Δ adapt split: a larger sample than the held-out bucket) and on the domain's test split from the report's \
         evaluations (Δ test). A decision *agrees* when it passes a model whose accuracy rose and rejects one whose \
         accuracy fell. {trained}\n\n",
        machine(),
        seconds,
        args.source.display(),
        args.adapted.display(),
        config.margin_gain,
        config.flip_se,
        config.entropy_drop,
        config.entropy_floor,
    );
    if let Some(note) = &args.note {
        md.push_str(&format!("Note: {note}\n\n"));
    }
    md.push_str(
        "| domain | n | flip rate src → adapted (needs) | median margin src → adapted (needs) | azimuth entropy src → adapted (needs) | decision | Δ held-out | Δ adapt split | agrees (adapt) | Δ test (z) | agrees (test) |\n\
         |---|---:|---|---|---|---|---:|---:|---|---:|---|\n",
    );
    md
}

/// One domain's decision against its accuracy changes: its Markdown row and its JSON (counted
/// into `totals`).
fn domain_report(r: &DomainResult, config: &GateConfig, totals: &mut Totals) -> Result<(String, Value)> {
    let d = r.decide(config)?;
    let (s, a) = r.adapt_accuracy()?;
    let held_change = a - s;
    let (split_s, split_a, split_n) = r.adapt_split;
    let adapt_change = split_a - split_s;
    let test_change = r.test.map(|t| t.change());
    let ok_adapt = agrees(d.passed, adapt_change);
    let ok_test = test_change.and_then(|c| agrees(d.passed, c));
    if let (Some(t), Some(ok)) = (r.test, ok_test)
        && t.paired.significant()
    {
        totals.counted_significant += 1;
        totals.agree_significant += usize::from(ok);
    }
    for (ok, agree, counted) in [
        (ok_adapt, &mut totals.agree_adapt, &mut totals.counted_adapt),
        (ok_test, &mut totals.agree_test, &mut totals.counted_test),
    ] {
        if let Some(ok) = ok {
            *counted += 1;
            *agree += usize::from(ok);
        }
    }
    totals.passed += usize::from(d.passed);
    let row = format!(
        "| {} | {} | {} | {} | {} | {} | {:+.3} | {:+.3} | {} | {} | {} |\n",
        r.domain,
        r.images.len(),
        criterion_cell(&d, "flip_consistency", 3),
        criterion_cell(&d, "score_margin", 4),
        criterion_cell(&d, "pose_diversity", 3),
        if d.passed { "PASS" } else { "REJECT" },
        held_change,
        adapt_change,
        fmt_agree(ok_adapt),
        r.test.map_or("n/a".into(), |t| format!("{:+.3} ({:+.1})", t.change(), t.paired.z())),
        if test_change.is_some() { fmt_agree(ok_test) } else { "n/a" },
    );
    let value = json!({
        "images": r.images.len(),
        "candidate_trained_on": r.trained_on,
        "decision": d,
        "reason": d.reason(),
        "held_out_acc_pi_6": {"source": s, "adapted": a, "change": held_change},
        "adapt_split_acc_pi_6": {"source": split_s, "adapted": split_a, "change": adapt_change, "images": split_n, "agrees": ok_adapt},
        "test_acc_pi_6": r.test.map(|t| json!({
            "source": t.source, "adapted": t.adapted, "change": t.change(), "agrees": ok_test,
            "lost": t.paired.lost, "gained": t.paired.gained, "mcnemar_z": t.paired.z(),
            "significant": t.paired.significant(),
        })),
        "per_image": per_image_json(r),
    });
    Ok((row, value))
}

/// A criterion of the decision as `active → candidate (≥ threshold)`, marked when it failed.
fn criterion_cell(d: &Decision, name: &str, digits: usize) -> String {
    let c = d.criteria.iter().find(|c| c.name == name).expect("criterion");
    format!(
        "{:.digits$} → {:.digits$} (≥ {:.digits$}){}",
        c.active,
        c.candidate,
        c.threshold,
        if c.passed { "" } else { " ✗" }
    )
}

/// Per image, in `images` order (columns keep the report small): each model's checks and its
/// error against the label, enough to re-decide or re-score offline.
fn per_image_json(r: &DomainResult) -> Value {
    let round = |v: f64, digits: i32| (v * 10f64.powi(digits)).round() / 10f64.powi(digits);
    let columns = |m: &[Measured]| {
        json!({
            "azimuth_deg": m.iter().map(|m| round(m.check.azimuth.to_degrees(), 4)).collect::<Vec<_>>(),
            "score": m.iter().map(|m| round(m.check.score, 7)).collect::<Vec<_>>(),
            "margin": m.iter().map(|m| round(m.check.margin, 7)).collect::<Vec<_>>(),
            "flip_consistent": m.iter().map(|m| m.check.flip_consistent).collect::<Vec<_>>(),
            "error_deg": m.iter().zip(&r.truth)
                .map(|(m, t)| round(pose_error(Some(angles(&m.pose)), angles(t)).to_degrees(), 4))
                .collect::<Vec<_>>(),
        })
    };
    json!({"image": r.images, "source": columns(&r.active), "adapted": columns(&r.candidate)})
}

/// The Markdown section on the `margin_gain` sweep.
fn sweep_markdown(results: &[DomainResult], config: &GateConfig, chosen: f64, sweep: &[SweepRow]) -> String {
    let lo = results.iter().map(|r| r.images.len()).min().unwrap_or(0);
    let hi = results.iter().map(|r| r.images.len()).max().unwrap_or(0);
    let mut md = format!(
        "## Choosing `margin_gain` (adapt split only)\n\n\
         For each value, how many domains' decisions agree with the sign of the adapt-split Δ (of those that \
         changed). The best is {chosen} (ties to the smallest positive value: with 0, a no-op adaptation that \
         changed nothing would pass); the decisions above use {}. For comparison, the \
         agreement with the sign of Δ on the gate's images alone ({lo}–{hi} images per domain, where a change of \
         one or two images decides the sign); it was not used to choose.\n\n\
         | margin_gain | agree (adapt split) | agree (held-out only) |\n|---:|---:|---:|\n",
        config.margin_gain
    );
    for r in sweep {
        md.push_str(&format!(
            "| {:.4} | {} / {} | {} / {} |\n",
            r.gain, r.adapt.0, r.adapt.1, r.held_out.0, r.held_out.1
        ));
    }
    md
}
