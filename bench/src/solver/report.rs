//! The solver benchmark's report: its aggregates, the JSON and the Markdown twin.

use anyhow::{Result, bail};
use serde_json::{Value, json};
use udapose_engine::solver::{AdamConfig, Optimizer, Prune};
use udapose_engine::{PoseMetrics, rotation_error};
use udapose_lab::atomic::write_atomic;

use super::{Row, Run, Solved, mean, median, paired_accuracy};
use crate::harness::{git_commit, load_average};

/// The aggregates over every image.
struct Summary {
    fast: PoseMetrics,
    fixed: PoseMetrics,
    method: PoseMetrics,
    rasterised: PoseMetrics,
    reference: PoseMetrics,
    backbone_ms: f64,
    fast_ms: f64,
    fixed_ms: f64,
    method_ms: f64,
    rasterised_ms: f64,
    reference_ms: f64,
    end_to_end: f64,
    /// Means per image (ms): load (decode + tensor), backbone, similarity, grid, refine.
    load_ms: f64,
    similarity_ms: f64,
    grid_ms: f64,
    refine_ms: f64,
    /// Mean loss evaluations per image.
    fast_evaluations: f64,
    fixed_evaluations: f64,
    rasterised_evaluations: f64,
    backbone_median: f64,
    fast_median: f64,
    fixed_median: f64,
    method_median: f64,
    rasterised_median: f64,
    reference_median: f64,
    n: usize,
    same_inits: usize,
    disagreement: f64,
    reference_lower: usize,
    paired: Value,
}

impl Summary {
    fn of(rows: &[Row]) -> Result<Summary> {
        let metrics = |pick: fn(&Row) -> &Solved| -> Result<PoseMetrics> {
            Ok(PoseMetrics::from_errors(&rows.iter().map(|r| pick(r).error).collect::<Vec<_>>())?)
        };
        let (fast, method, reference) = (metrics(|r| &r.fast)?, metrics(|r| &r.method)?, metrics(|r| &r.reference)?);
        let backbone_ms = mean(rows.iter().map(|r| r.backbone_ms));
        let load_ms = mean(rows.iter().map(|r| r.load_ms));
        let fast_ms = mean(rows.iter().map(|r| r.fast.ms));
        let both = |r: &Row| r.fast.pose.zip(r.reference.pose);
        let evaluations = |pick: fn(&Row) -> &Solved| mean(rows.iter().map(|r| pick(r).evaluations as f64));
        Ok(Summary {
            fast,
            fixed: metrics(|r| &r.fixed)?,
            method,
            rasterised: metrics(|r| &r.rasterised)?,
            reference,
            backbone_ms,
            fast_ms,
            fixed_ms: mean(rows.iter().map(|r| r.fixed.ms)),
            method_ms: mean(rows.iter().map(|r| r.method.ms)),
            rasterised_ms: mean(rows.iter().map(|r| r.rasterised.ms)),
            reference_ms: mean(rows.iter().map(|r| r.reference.ms)),
            end_to_end: load_ms + backbone_ms + fast_ms,
            load_ms,
            similarity_ms: mean(rows.iter().map(|r| r.stages.similarity)),
            grid_ms: mean(rows.iter().map(|r| r.stages.grid)),
            refine_ms: mean(rows.iter().map(|r| r.stages.refine)),
            fast_evaluations: evaluations(|r| &r.fast),
            fixed_evaluations: evaluations(|r| &r.fixed),
            rasterised_evaluations: evaluations(|r| &r.rasterised),
            backbone_median: median(rows.iter().map(|r| r.backbone_ms)),
            fast_median: median(rows.iter().map(|r| r.fast.ms)),
            fixed_median: median(rows.iter().map(|r| r.fixed.ms)),
            method_median: median(rows.iter().map(|r| r.method.ms)),
            rasterised_median: median(rows.iter().map(|r| r.rasterised.ms)),
            reference_median: median(rows.iter().map(|r| r.reference.ms)),
            n: rows.len(),
            same_inits: rows.iter().filter(|r| r.same_inits).count(),
            disagreement: median(
                rows.iter().filter_map(both).map(|(a, b)| rotation_error(&a.rotation(), &b.rotation()).to_degrees()),
            ),
            reference_lower: rows.iter().filter(|r| r.reference.loss < r.fast.loss).count(),
            paired: paired_accuracy(rows),
        })
    }
}

/// Where the run happened, read once its measurements are done.
struct Machine {
    commit: String,
    cpu: String,
    threads: usize,
    load_after: String,
}

/// Writes `--out` (JSON) and its Markdown twin, and prints the headline.
pub(super) fn write(run: &Run, rows: &[Row]) -> Result<()> {
    let s = Summary::of(rows)?;
    let machine = Machine {
        commit: git_commit(),
        cpu: udapose_engine::runtime::cpu_model(),
        threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
        load_after: load_average(),
    };
    let Optimizer::Adam(fast_adam) = &run.solver.config.optimizer else { bail!("the default optimiser is Adam") };
    let mut report = measurements_json(rows, &s);
    let Value::Object(setup) = setup_json(run, &machine) else { unreachable!("a JSON object") };
    report.as_object_mut().expect("a JSON object").extend(setup);
    let md = header_markdown(run, &s, &machine)
        + &table_markdown(&s, fast_adam, &run.solver.config.prune)
        + &findings_markdown(run, &s);
    let args = run.args;
    if let Some(dir) = args.out.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir)?;
    }
    write_atomic(&args.out, (serde_json::to_string_pretty(&report)? + "\n").as_bytes())?;
    write_atomic(&args.out.with_extension("md"), md.as_bytes())?;
    let pct = |x: f64| 100.0 * x;
    let (fast_ms, reference_ms, end_to_end) = (s.fast_ms, s.reference_ms, s.end_to_end);
    eprintln!(
        "udapose {fast_ms:.1} ms/image (Acc@π/6 {:.3}), reference {reference_ms:.1} ms/image (Acc@π/6 {:.3}): \
         {:.0}× faster; end to end {end_to_end:.1} ms, backbone {:.0}%. Wrote {} and .md",
        s.fast.acc_pi_6,
        s.reference.acc_pi_6,
        reference_ms / fast_ms,
        pct(s.backbone_ms / end_to_end),
        args.out.display()
    );
    Ok(())
}

/// The report's timings, accuracies and per-image measurements.
fn measurements_json(rows: &[Row], s: &Summary) -> Value {
    let failures = |pick: fn(&Row) -> &Solved| rows.iter().filter(|r| pick(r).pose.is_none()).count();
    let (backbone_ms, fast_ms, reference_ms, end_to_end) = (s.backbone_ms, s.fast_ms, s.reference_ms, s.end_to_end);
    let (backbone_median, fast_median) = (s.backbone_median, s.fast_median);
    json!({
        "udapose_ms_per_image": fast_ms,
        "reference_ms_per_image": reference_ms,
        "speedup": reference_ms / fast_ms,
        "udapose_acc_pi_6": s.fast.acc_pi_6,
        "reference_acc_pi_6": s.reference.acc_pi_6,
        "end_to_end_ms": end_to_end,
        "backbone_share": backbone_ms / end_to_end,
        "backbone_ms_per_image": backbone_ms,
        "backbone_median_ms": backbone_median,
        "end_to_end_median_ms": backbone_median + fast_median,
        "backbone_share_median": backbone_median / (backbone_median + fast_median),
        "end_to_end_note": "load (PNG decode + tensor) + backbone + udapose's default solver",
        "udapose_median_ms": fast_median,
        "reference_median_ms": s.reference_median,
        "udapose_metrics": s.fast,
        "reference_metrics": s.reference,
        "breakdown_ms": {
            "decode_crop": s.load_ms,
            "backbone": backbone_ms,
            "similarity": s.similarity_ms,
            "grid": s.grid_ms,
            "refine": s.refine_ms,
            "total": end_to_end,
        },
        "solver_share": fast_ms / end_to_end,
        "evaluations_per_image": {"udapose": s.fast_evaluations, "udapose_fixed": s.fixed_evaluations},
        "udapose_fixed_schedule": {
            "note": "the fixed 150-step schedule without plateau stopping or pruning (the default before them), on the same images",
            "ms_per_image": s.fixed_ms,
            "median_ms": s.fixed_median,
            "metrics": s.fixed,
            "paired": s.paired["udapose_vs_fixed"],
        },
        "udapose_rasterised": {
            "note": "udapose's default solver with every pose rasterised (S still computed lazily): the solver before the ray caster, on the same images",
            "ms_per_image": s.rasterised_ms,
            "median_ms": s.rasterised_median,
            "evaluations_per_image": s.rasterised_evaluations,
            "metrics": s.rasterised,
            "paired": s.paired["udapose_vs_rasterised"],
        },
        "udapose_method_steps": {
            "note": "udapose's solver with METHOD's 300-step schedule (the reference's), for a same-steps comparison",
            "ms_per_image": s.method_ms,
            "speedup": reference_ms / s.method_ms,
            "metrics": s.method,
        },
        "same_inits": s.same_inits,
        "reference_lower_loss": s.reference_lower,
        "median_disagreement_deg": s.disagreement,
        "failures": {"udapose": failures(|r| &r.fast), "reference": failures(|r| &r.reference)},
        "n": s.n,
        "paired": s.paired,
        "images": per_image_json(rows),
    })
}

fn per_image_json(rows: &[Row]) -> Vec<Value> {
    let solved = |s: &Solved| {
        json!({
            "ms": s.ms,
            "pose": s.pose.map(|p| [p.azimuth, p.elevation, p.theta, p.distance]),
            "loss": s.loss,
            "error_deg": s.error.to_degrees(),
            "evaluations": s.evaluations,
        })
    };
    rows.iter()
        .map(|r| {
            json!({
                "name": r.name,
                "truth": [r.truth.azimuth, r.truth.elevation, r.truth.theta, r.truth.distance],
                "backbone_ms": r.backbone_ms,
                "load_ms": r.load_ms,
                "udapose": solved(&r.fast),
                "udapose_stages_ms": [r.stages.similarity, r.stages.grid, r.stages.refine],
                "udapose_fixed": solved(&r.fixed),
                "udapose_method": solved(&r.method),
                "udapose_rasterised": solved(&r.rasterised),
                "reference": solved(&r.reference),
                "same_inits": r.same_inits,
            })
        })
        .collect()
}

/// The report's settings: the solvers, the model and data, the machine, the command.
fn setup_json(run: &Run, machine: &Machine) -> Value {
    let (args, config, reference_config) = (run.args, &run.solver.config, &run.reference_config);
    json!({
        "grid": [run.grid.height, run.grid.width],
        "crop": run.model.manifest.crop,
        "hypotheses": config.hypotheses,
        "udapose_optimizer": config.optimizer,
        "udapose_prune": config.prune,
        "reference_optimizer": {
            "adam": reference_config.adam,
            "parallel_hypotheses": reference_config.parallel_hypotheses,
            "torch_threads": args.reference_torch_threads,
            "rendering": "tch autograd ops per step (projection, perspective-correct barycentrics, feature render, per-pixel dot product); face assignment from udapose's rasteriser",
        },
        "model": run.model.manifest.version,
        "model_dir": args.model.display().to_string(),
        "data": args.data.display().to_string(),
        "domain": args.domain,
        "split": args.split.join(","),
        "machine": {
            "cpu": machine.cpu,
            "threads": machine.threads,
            "torch_threads": run.torch_threads,
            "rayon_threads": rayon::current_num_threads(),
            "load_average_before": run.load_before,
            "load_average_after": machine.load_after,
        },
        "commit": machine.commit,
        "command": run.command,
        "note": args.note,
        "timing": "mean wall-clock ms per image after one untimed warm-up image; load: PNG decode and input tensor (breakdown_ms.decode_crop); backbone: one image per batch on the CPU; udapose: render_and_compare (similarity GEMM, multi-pose init, k refinements); reference: udapose's multi-pose init then k autograd refinements",
    })
}

/// The Markdown's title, command and conditions.
fn header_markdown(run: &Run, s: &Summary, machine: &Machine) -> String {
    let (args, config) = (run.args, &run.solver.config);
    let [h, w] = run.model.manifest.crop;
    let (command, load_before, n, same_inits) = (&run.command, &run.load_before, s.n, s.same_inits);
    let Machine { commit, cpu, threads, load_after } = machine;
    format!(
        "# Solver benchmark: udapose vs the autograd reference\n\n\
         `{command}`\n\n\
         Model `{version}` ({backbone:?}, D = {dim}), {n} images of `{domain}/{split}` ({h}×{w} crops, \
         {gh}×{gw} feature grid), k = {k} hypotheses from the same grid poses ({same_inits}/{n} images checked \
         identical). Machine: {cpu}, {threads} threads (torch {tt}, rayon {rt}; the reference runs with torch \
         {rtt}); load average {load_before} before, {load_after} after. Commit `{commit}`.\n\n",
        version = run.model.manifest.version,
        backbone = run.model.manifest.backbone,
        dim = run.solver.dim(),
        domain = args.domain,
        split = args.split.join(","),
        gh = run.grid.height,
        gw = run.grid.width,
        k = config.hypotheses,
        tt = run.torch_threads,
        rtt = args.reference_torch_threads,
        rt = rayon::current_num_threads(),
    )
}

/// The Markdown's table of the four solvers and the default's stages.
fn table_markdown(s: &Summary, fast: &AdamConfig, prune: &Prune) -> String {
    let (fast_ms, fixed_ms, method_ms, reference_ms) = (s.fast_ms, s.fixed_ms, s.method_ms, s.reference_ms);
    let (m_fast, m_fixed, m_method, m_ref) = (&s.fast, &s.fixed, &s.method, &s.reference);
    let pct = |x: f64| 100.0 * x / s.end_to_end;
    format!(
        "| solver | ms per image (mean) | median | evaluations | Acc@π/6 | Acc@π/18 | MedErr (°) |\n\
         |---|---:|---:|---:|---:|---:|---:|\n\
         | udapose (Adam ≤ {fs} steps, plateau {pat}, pruned after {pa} at {pm}) | {fast_ms:.1} | {fast_med:.1} | {fe:.0} | {fa:.3} | {fb:.3} | {fc:.1} |\n\
         | udapose, fixed {fs} steps, no pruning | {fixed_ms:.1} | {fixed_med:.1} | {xe:.0} | {xa:.3} | {xb:.3} | {xc:.1} |\n\
         | udapose's default, every pose rasterised (before the ray caster) | {rast_ms:.1} | {rast_med:.1} | {re:.0} | {rsa:.3} | {rsb:.3} | {rsc:.1} |\n\
         | udapose, METHOD's 300 steps | {method_ms:.1} | {method_med:.1} | | {ma:.3} | {mb:.3} | {mc:.1} |\n\
         | reference (tch autograd render, Adam 300 steps) | {reference_ms:.1} | {ref_med:.1} | | {ra:.3} | {rb:.3} | {rc:.1} |\n\n\
         | stage (udapose's default) | ms per image (mean) | share of end to end |\n\
         |---|---:|---:|\n\
         | decode + tensor (the crop is the image) | {load:.2} | {load_pct:.1}% |\n\
         | backbone | {bb:.2} | {bb_pct:.1}% |\n\
         | features transposed, clutter map (S is computed as read) | {sim:.2} | {sim_pct:.1}% |\n\
         | grid, 144 poses from cached renders (S entries computed here) | {grid:.2} | {grid_pct:.1}% |\n\
         | refine, k hypotheses | {refine:.2} | {refine_pct:.1}% |\n\
         | **total** | {total:.2} | solver {solver_pct:.1}% |\n\n",
        fs = fast.steps,
        pat = fast.patience,
        pa = prune.after,
        pm = prune.margin,
        fe = s.fast_evaluations,
        xe = s.fixed_evaluations,
        rast_ms = s.rasterised_ms,
        rast_med = s.rasterised_median,
        re = s.rasterised_evaluations,
        rsa = s.rasterised.acc_pi_6,
        rsb = s.rasterised.acc_pi_18,
        rsc = s.rasterised.med_err_deg,
        fixed_med = s.fixed_median,
        xa = m_fixed.acc_pi_6,
        xb = m_fixed.acc_pi_18,
        xc = m_fixed.med_err_deg,
        load = s.load_ms,
        load_pct = pct(s.load_ms),
        bb = s.backbone_ms,
        bb_pct = pct(s.backbone_ms),
        sim = s.similarity_ms,
        sim_pct = pct(s.similarity_ms),
        grid = s.grid_ms,
        grid_pct = pct(s.grid_ms),
        refine = s.refine_ms,
        refine_pct = pct(s.refine_ms),
        total = s.end_to_end,
        solver_pct = pct(fast_ms),
        fast_med = s.fast_median,
        method_med = s.method_median,
        ref_med = s.reference_median,
        fa = m_fast.acc_pi_6,
        fb = m_fast.acc_pi_18,
        fc = m_fast.med_err_deg,
        ma = m_method.acc_pi_6,
        mb = m_method.acc_pi_18,
        mc = m_method.med_err_deg,
        ra = m_ref.acc_pi_6,
        rb = m_ref.acc_pi_18,
        rc = m_ref.med_err_deg,
    )
}

/// The Markdown's speedup, paired comparison, end-to-end latency and remarks.
fn findings_markdown(run: &Run, s: &Summary) -> String {
    let pct = |x: f64| 100.0 * x;
    let (backbone_ms, end_to_end, backbone_median, fast_median) =
        (s.backbone_ms, s.end_to_end, s.backbone_median, s.fast_median);
    let (disagreement, reference_lower, n, paired) = (s.disagreement, s.reference_lower, s.n, &s.paired);
    format!(
        "**Speedup** (reference / udapose, mean ms per image): **{speedup:.0}×** ({speedup300:.0}× against udapose \
         at the reference's 300 steps).\n\n\
         **Paired** (Acc@π/6 on the same images): udapose alone right on {only_u}, the reference alone on \
         {only_r}; difference {pd:+.3} [{plo:+.3}, {phi:+.3}] (95% paired bootstrap). Against the fixed \
         schedule: the default alone right on {only_d}, the fixed schedule alone on {only_f}; difference \
         {fd:+.3} [{flo:+.3}, {fhi:+.3}]. Against the same solver rasterised (the solver before the ray \
         caster): the default alone right on {only_c}, the rasterised one alone on {only_s}; difference \
         {cd:+.3} [{clo:+.3}, {chi:+.3}].\n\n\
         **End to end** (load + backbone + udapose solver): {end_to_end:.1} ms per image, of which the backbone is \
         {backbone_ms:.1} ms (**{share:.0}%**); by medians, {e2e_median:.1} ms of which the backbone is \
         {backbone_median:.1} ms ({share_median:.0}%).\n\n\
         The two solvers' estimates differ by {disagreement:.1}° (median); the reference reached a lower loss on \
         {reference_lower}/{n} images. Times are wall-clock means after one untimed warm-up image; the solvers \
         are timed on features already computed. The reference renders with autograd ops at every step (projection, perspective-correct \
         barycentrics, feature render, per-pixel dot product with F); its face assignment comes from \
         udapose's rasteriser, so it is a lower bound on a PyTorch3D renderer's cost. It refines the k \
         hypotheses {order}.\n{note}",
        only_u = paired["udapose"]["only_udapose_right"],
        only_r = paired["udapose"]["only_reference_right"],
        pd = paired["udapose"]["acc_pi_6_difference"].as_f64().unwrap_or(f64::NAN),
        plo = paired["udapose"]["ci95"][0].as_f64().unwrap_or(f64::NAN),
        phi = paired["udapose"]["ci95"][1].as_f64().unwrap_or(f64::NAN),
        only_d = paired["udapose_vs_fixed"]["only_udapose_right"],
        only_f = paired["udapose_vs_fixed"]["only_reference_right"],
        fd = paired["udapose_vs_fixed"]["acc_pi_6_difference"].as_f64().unwrap_or(f64::NAN),
        flo = paired["udapose_vs_fixed"]["ci95"][0].as_f64().unwrap_or(f64::NAN),
        fhi = paired["udapose_vs_fixed"]["ci95"][1].as_f64().unwrap_or(f64::NAN),
        only_c = paired["udapose_vs_rasterised"]["only_udapose_right"],
        only_s = paired["udapose_vs_rasterised"]["only_reference_right"],
        cd = paired["udapose_vs_rasterised"]["acc_pi_6_difference"].as_f64().unwrap_or(f64::NAN),
        clo = paired["udapose_vs_rasterised"]["ci95"][0].as_f64().unwrap_or(f64::NAN),
        chi = paired["udapose_vs_rasterised"]["ci95"][1].as_f64().unwrap_or(f64::NAN),
        e2e_median = backbone_median + fast_median,
        share_median = pct(backbone_median / (backbone_median + fast_median)),
        speedup = s.reference_ms / s.fast_ms,
        speedup300 = s.reference_ms / s.method_ms,
        share = pct(backbone_ms / end_to_end),
        note = run.args.note.as_ref().map(|n| format!("\nNote: {n}\n")).unwrap_or_default(),
        order = if run.reference_config.parallel_hypotheses {
            "concurrently, as udapose does"
        } else {
            "one after the other"
        },
    )
}
