//! The mechanics of 3DUDA's EM loop and of the oracle on a small random model: the source is
//! never modified, progress arrives phase by phase, cancellation stops the run, the firing test
//! gates every update, the oracle takes exactly its budget (or trains to a plateau) and leaves
//! occluded vertices out. (Whether adaptation *helps* is
//! measured on real data: lab/tests/adapt.rs and reports/syncar-ood.md.)

mod support;

use std::ops::ControlFlow;

use tch::{Device, Kind, Tensor, nn};
use udapose_engine::Pose;
use udapose_engine::adapt::{self, AdaptConfig, Budget, Event, Label, Phase, Positives, Selection, Threshold};
use udapose_engine::checkpoint;
use udapose_engine::error::EngineError;
use udapose_engine::solver::{AdamConfig, Optimizer, SolverConfig};

/// The shared random model, saved and loaded back (as a served model is).
fn random_model(name: &str) -> checkpoint::Model {
    let scratch = support::Scratch::new(&format!("adapt-{name}"));
    let model = support::random_model(5, [64, 160], "source-test");
    let path = scratch.path().join("model");
    checkpoint::save(&path, &model.manifest, &model.vs, &model.neural_mesh).unwrap();
    checkpoint::load(&path, Device::Cpu).unwrap()
}

fn images(n: i64) -> Tensor {
    seeded_images(n, 11)
}

/// `n` images of uniform noise, the same for the same `seed` (drawn on the host: see
/// [`support::Draws`]).
fn seeded_images(n: i64, seed: i64) -> Tensor {
    support::Draws::new(seed as u64).rand(&[n, 3, 64, 160])
}

/// Small and fast: 4 images per vertex update, 3 per backbone step, a short solver.
fn config(threshold: f64) -> AdaptConfig {
    let solver = SolverConfig {
        optimizer: Optimizer::Adam(AdamConfig { steps: 10, ..AdamConfig::default() }),
        ..SolverConfig::default()
    };
    AdaptConfig {
        threshold: Threshold::Fixed(threshold),
        vertex_batch: 4,
        batch: 3,
        max_rounds: 2,
        solver,
        ..AdaptConfig::default()
    }
}

fn snapshot(vs: &nn::VarStore) -> Vec<(String, Tensor)> {
    let mut v: Vec<(String, Tensor)> = vs.variables().into_iter().map(|(k, t)| (k, t.copy())).collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

fn same(a: &[(String, Tensor)], b: &[(String, Tensor)]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|((ka, ta), (kb, tb))| ka == kb && ta.equal(tb))
}

#[test]
fn adaptation_leaves_the_source_alone_and_reports_each_phase() {
    let source = random_model("phases");
    let before = snapshot(&source.vs);
    let c_before = source.neural_mesh.vertex_features.copy();
    let mut phases = Vec::new();
    let mut rounds = 0;
    // τ = −1: every visible vertex fires, so every stage has work to do.
    let adapted = adapt::adapt(&source, &images(6), &config(-1.0), &mut |e| {
        match e {
            Event::Step { phase, .. } if phases.last() != Some(&phase) => phases.push(phase),
            Event::Round(r) => {
                rounds += 1;
                assert_eq!(r.round, rounds);
                assert!((0.0..=1.0).contains(&r.fired_ratio) && r.vertices_updated > 0.0);
            }
            _ => {}
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    use Phase::*;
    assert_eq!(phases, [Features, VertexUpdate, PseudoPoses, Backbone, Features, VertexUpdate, PseudoPoses]);
    assert_eq!((rounds, adapted.rounds.len()), (2, 2), "the last round has no backbone step");
    assert!(same(&before, &snapshot(&source.vs)), "the source backbone changed");
    assert!(source.neural_mesh.vertex_features.equal(&c_before), "the source vertex features changed");
    assert!(!same(&before, &snapshot(&adapted.vs)), "the adapted backbone was not trained");
    let trained = adapted.rounds[0].images_trained;
    assert_eq!(adapted.backbone_steps, trained.div_ceil(3));
    let c = &adapted.neural_mesh.vertex_features;
    assert!(!c.equal(&c_before));
    let norms = c.norm_scalaropt_dim(2, [1], false);
    assert!(f64::try_from((norms - 1.0).abs().max()).unwrap() < 1e-5, "vertex features stay unit vectors");
    assert_eq!(adapted.pseudo_poses.len(), 6);
}

#[test]
fn nothing_fires_above_a_cosine_of_one_so_nothing_changes() {
    let source = random_model("nofire");
    let before = snapshot(&source.vs);
    let frozen = AdaptConfig { target_batchnorm: false, ..config(1.0) };
    let adapted = adapt::adapt(&source, &images(4), &frozen, &mut |_| ControlFlow::Continue(())).unwrap();
    for r in &adapted.rounds {
        assert_eq!((r.fired_ratio, r.vertices_updated, r.images_trained), (0.0, 0.0, 0));
    }
    assert_eq!(adapted.backbone_steps, 0);
    assert!(same(&before, &snapshot(&adapted.vs)));
    assert!(adapted.neural_mesh.vertex_features.equal(&source.neural_mesh.vertex_features));

    // With the default AdaBN step, only the BatchNorm statistics move.
    let adapted = adapt::adapt(&source, &images(4), &config(1.0), &mut |_| ControlFlow::Continue(())).unwrap();
    let is_stat = |k: &str| k.ends_with(".running_mean") || k.ends_with(".running_var");
    let split = |v: Vec<(String, Tensor)>| v.into_iter().partition::<Vec<_>, _>(|(k, _)| is_stat(k));
    let ((stats_before, weights_before), (stats_after, weights_after)) =
        (split(snapshot(&source.vs)), split(snapshot(&adapted.vs)));
    assert!(same(&weights_before, &weights_after), "a weight changed although nothing fired");
    assert!(!same(&stats_before, &stats_after), "the BatchNorm statistics were not re-estimated");
    assert!(adapted.neural_mesh.vertex_features.equal(&source.neural_mesh.vertex_features));
}

#[test]
fn batchnorm_only_moves_the_statistics_and_skips_the_rounds() {
    let source = random_model("bnonly");
    let bn = AdaptConfig { alpha: 1.0, update_backbone: false, ..config(-1.0) };
    assert!(bn.batchnorm_only() && !config(-1.0).batchnorm_only());
    assert!(!AdaptConfig { update_clutter: true, ..bn.clone() }.batchnorm_only(), "the clutter would move");
    let mut events = 0;
    let adapted = adapt::adapt(&source, &images(4), &bn, &mut |_| {
        events += 1;
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!((adapted.rounds.len(), adapted.backbone_steps, events), (0, 0, 0), "no round ran");
    let is_stat = |k: &str| k.ends_with(".running_mean") || k.ends_with(".running_var");
    let split = |v: Vec<(String, Tensor)>| v.into_iter().partition::<Vec<_>, _>(|(k, _)| is_stat(k));
    let ((stats_before, weights_before), (stats_after, weights_after)) =
        (split(snapshot(&source.vs)), split(snapshot(&adapted.vs)));
    assert!(same(&weights_before, &weights_after));
    assert!(!same(&stats_before, &stats_after), "the BatchNorm statistics were not re-estimated");
    assert!(adapted.neural_mesh.vertex_features.equal(&source.neural_mesh.vertex_features));
    assert_eq!(adapted.pseudo_poses.len(), 4);
}

#[test]
fn the_backbone_trains_the_positives_it_is_told_to() {
    let source = random_model("positives");
    // τ = 0 on a random model: about half of the visible vertices fire.
    let run = |positives| {
        let config = AdaptConfig { positives, max_rounds: 1, min_fired_ratio: 0.0, drop_quantile: 0.0, ..config(0.0) };
        adapt::adapt(&source, &images(4), &config, &mut |_| ControlFlow::Continue(())).unwrap().rounds[0].clone()
    };
    let (visible, fired, object) = (run(Positives::Visible), run(Positives::Fired), run(Positives::Object));
    assert_eq!(visible.images_trained, 4);
    assert_eq!(visible.positive_share, 1.0, "eq. 8 trains every visible vertex");
    // The same images, the same pseudo-poses: the fired positives are exactly the fired share.
    assert!((fired.positive_share - fired.fired_ratio).abs() < 1e-9, "{fired:?}");
    assert!(fired.positive_share > 0.1 && fired.positive_share < 0.9, "{fired:?}");
    assert!(object.positive_share < 1.0, "{object:?}");
}

#[test]
fn the_global_filter_drops_images_below_omega() {
    let source = random_model("global");
    // With τ = −1 every vertex fires: Ω = 1 passes every image ...
    let all = AdaptConfig { selection: Selection::Global(1.0), max_rounds: 1, ..config(-1.0) };
    let a = adapt::adapt(&source, &images(4), &all, &mut |_| ControlFlow::Continue(())).unwrap();
    assert_eq!(a.rounds[0].images_selected, 4);
    // ... and with τ = 1 nothing fires, so Ω = 0.5 passes none.
    let none = AdaptConfig { selection: Selection::Global(0.5), max_rounds: 1, ..config(1.0) };
    let b = adapt::adapt(&source, &images(4), &none, &mut |_| ControlFlow::Continue(())).unwrap();
    assert_eq!((b.rounds[0].images_selected, b.rounds[0].vertices_updated), (0, 0.0));
}

#[test]
fn cancelling_stops_the_run() {
    let source = random_model("cancel");
    let mut seen = 0;
    let err = adapt::adapt(&source, &images(4), &config(-1.0), &mut |e| {
        seen += 1;
        if matches!(e, Event::Step { phase: Phase::VertexUpdate, .. }) {
            ControlFlow::Break(())
        } else {
            ControlFlow::Continue(())
        }
    })
    .err()
    .unwrap();
    assert_eq!(err, EngineError::Cancelled);
    assert!(seen >= 2);
}

fn labels(n: usize) -> Vec<Label> {
    (0..n).map(|i| Label { pose: Pose::new(0.5 * i as f64, 0.2, 0.0, 5.0), occluded: None }).collect()
}

fn go(_: Event) -> ControlFlow<()> {
    ControlFlow::Continue(())
}

#[test]
fn the_oracle_takes_exactly_its_budget() {
    let source = random_model("oracle");
    // 5 images in batches of 3: 2 steps per pass, so 5 steps take 3 passes.
    let tuned = adapt::finetune(&source, &images(5), &labels(5), Budget::Steps(5), &config(0.8), &mut go).unwrap();
    assert_eq!((tuned.backbone_steps, tuned.rounds.len()), (5, 3));
    assert!(!tuned.neural_mesh.vertex_features.equal(&source.neural_mesh.vertex_features), "C trains with labels");
    let wrong = adapt::finetune(&source, &images(5), &labels(4), Budget::Steps(5), &config(0.8), &mut go);
    assert!(matches!(wrong, Err(EngineError::InvalidInput(m)) if m.contains("4 poses for 5 images")));
}

#[test]
fn the_strong_oracle_trains_until_its_loss_stops_falling() {
    let source = random_model("plateau");
    let budget = |tolerance| Budget::Plateau { min_passes: 2, max_passes: 6, tolerance };
    // A tolerance no pass can beat stops at the minimum; none that every pass beats, at the most.
    let short = adapt::finetune(&source, &images(5), &labels(5), budget(1.0), &config(0.8), &mut go).unwrap();
    assert_eq!((short.rounds.len(), short.backbone_steps), (2, 4));
    let long = adapt::finetune(&source, &images(5), &labels(5), budget(-1e9), &config(0.8), &mut go).unwrap();
    assert_eq!((long.rounds.len(), long.backbone_steps), (6, 12));
}

#[test]
fn occluded_vertices_are_not_positives() {
    let source = random_model("occluded");
    let (h, w) = (64, 160);
    let mut covered = labels(2);
    covered.iter_mut().for_each(|l| l.occluded = Some(vec![true; h * w]));
    // Every vertex occluded: no image has a positive left to train.
    let none = adapt::finetune(&source, &images(2), &covered, Budget::Steps(1), &config(0.8), &mut go);
    assert!(matches!(none, Err(EngineError::InvalidInput(m)) if m.contains("no labelled image")));
    // Half the crop covered trains, and differently from no occluder.
    let mut half = labels(2);
    half.iter_mut().for_each(|l| l.occluded = Some((0..h * w).map(|p| p % w < w / 2).collect()));
    let open = adapt::finetune(&source, &images(2), &labels(2), Budget::Steps(1), &config(0.8), &mut go).unwrap();
    let masked = adapt::finetune(&source, &images(2), &half, Budget::Steps(1), &config(0.8), &mut go).unwrap();
    assert!(!masked.neural_mesh.vertex_features.equal(&open.neural_mesh.vertex_features));
    let mut wrong = labels(2);
    wrong[1].occluded = Some(vec![false; 10]);
    let err = adapt::finetune(&source, &images(2), &wrong, Budget::Steps(1), &config(0.8), &mut go);
    assert!(matches!(err, Err(EngineError::InvalidInput(m)) if m.contains("occluder mask of 10 pixels")));
}

#[test]
fn fired_matches_are_false_only_away_from_the_true_pose() {
    let source = random_model("false-fired");
    let dim = source.neural_mesh.vertex_features.size()[1] as usize;
    let camera = udapose_engine::Camera::for_crop(64, 160).unwrap();
    let (h, w) = (64 / 8, 160 / 8);
    let features = udapose_engine::estimator::Features { data: vec![0.1; dim * h * w], dim, height: h, width: w };
    let truth = Pose::new(0.4, 0.2, 0.0, 5.0);
    // A threshold every cosine passes: every visible vertex fires.
    let firing = adapt::FiringTest::new(&source.neural_mesh, &camera, 8, Threshold::Fixed(-2.0)).unwrap();
    let count = |pseudo: &Pose| firing.false_matches(&features, pseudo, &truth).unwrap();
    assert_eq!(firing.fired_ratio(&features, &truth).unwrap(), 1.0);
    let (fired, wrong) = count(&truth);
    assert!(fired > 10 && wrong == 0, "at the true pose: {wrong} of {fired} false");
    let (fired, wrong) = count(&Pose::new(0.4 + std::f64::consts::PI, 0.2, 0.0, 5.0));
    assert!(fired > 10 && wrong * 2 > fired, "turned around: only {wrong} of {fired} false");
}

/// The target check's reading alone is round 1's `source_fired_ratio`, bit for bit.
#[test]
fn the_source_check_reads_what_round_one_reports() {
    let source = random_model("source-check");
    let one = AdaptConfig { max_rounds: 1, ..config(0.0) };
    let images = images(6);
    let each = adapt::source_fired(&source, &images, &one, &mut go).unwrap();
    assert_eq!(each.len(), 6);
    let alone = each.iter().sum::<f64>() / 6.0;
    let mut checks = Vec::new();
    let mut record = |e: Event| {
        if let Event::TargetCheck { fired } = e {
            checks.push(fired);
        }
        ControlFlow::Continue(())
    };
    let round = adapt::adapt(&source, &images, &one, &mut record).unwrap().rounds[0].clone();
    assert_eq!(Some(alone), round.source_fired_ratio);
    assert_eq!(checks, [alone], "one TargetCheck event, the same reading");
    assert!(alone > 0.0 && alone < 1.0, "τ = 0 fires some vertices of a random model, not all: {alone}");
}

/// A caller that refuses the images at the target check stops the run before any round.
#[test]
fn breaking_at_the_target_check_runs_no_round() {
    let source = random_model("source-check");
    let mut seen = Vec::new();
    let mut refuse = |e: Event| match e {
        Event::TargetCheck { .. } => {
            seen.push("check".to_string());
            ControlFlow::Break(())
        }
        Event::Step { phase, .. } => {
            seen.push(format!("{phase:?}"));
            ControlFlow::Continue(())
        }
        _ => {
            seen.push("other".to_string());
            ControlFlow::Continue(())
        }
    };
    let run = adapt::adapt(&source, &images(6), &config(0.0), &mut refuse);
    assert!(matches!(run, Err(EngineError::Cancelled)), "refused at the check");
    assert_eq!(seen.last().map(String::as_str), Some("check"), "nothing after the check: {seen:?}");
    assert!(seen.iter().all(|s| s == "Features" || s == "check"), "only the check's own features ran: {seen:?}");
}

#[test]
fn bad_inputs_are_errors() {
    let source = random_model("bad");
    let go = &mut |_: Event| ControlFlow::Continue(());
    let wrong_size = Tensor::rand([2, 3, 64, 128], (Kind::Float, Device::Cpu));
    assert!(
        matches!(adapt::adapt(&source, &wrong_size, &config(0.8), go), Err(EngineError::InvalidInput(m)) if m.contains("N×3×64×160"))
    );
    let empty = Tensor::zeros([0, 3, 64, 160], (Kind::Float, Device::Cpu));
    assert!(adapt::adapt(&source, &empty, &config(0.8), go).is_err());
    let bad = AdaptConfig { alpha: 1.5, ..config(0.8) };
    assert!(adapt::adapt(&source, &images(2), &bad, go).is_err());
}

#[test]
fn the_flip_check_keeps_only_flip_consistent_pseudo_poses() {
    let source = random_model("flip");
    // τ = −1, ψ = 0 and no score quantile: every image would train but for the flip check.
    // α = 1 keeps `C` as it is, so the vertex update's solves see the flips the round's
    // pseudo-poses see (the clutter update only keeps the run from being BatchNorm-only).
    let base = AdaptConfig {
        max_rounds: 1,
        min_fired_ratio: 0.0,
        drop_quantile: 0.0,
        alpha: 1.0,
        update_clutter: true,
        ..config(-1.0)
    };
    let mut agreeing_seen = Vec::new();
    for seed in 11..15 {
        let images = seeded_images(8, seed);
        let run = |config: &AdaptConfig| adapt::adapt(&source, &images, config, &mut go).unwrap().rounds[0].clone();
        let plain = run(&base);
        assert_eq!((plain.images_trained, plain.flip_consistent), (8, None));
        assert!(plain.vertices_updated > 0.0, "{plain:?}");
        let checked = run(&AdaptConfig { flip_check: true, ..base.clone() });
        let agreeing = checked.flip_consistent.expect("the flip check counts its images");
        assert_eq!(checked.images_trained, agreeing, "{checked:?}");
        assert!(agreeing < 8, "a random model's estimates cannot all mirror: {checked:?}");
        // Only flip-consistent images move vertices: none when none agrees.
        assert_eq!(checked.vertices_updated > 0.0, agreeing > 0, "{checked:?}");
        agreeing_seen.push(agreeing);
    }
    assert!(agreeing_seen.contains(&0) && agreeing_seen.iter().any(|&a| a > 0), "both cases: {agreeing_seen:?}");
}

/// Rounds without their wall time, to compare two runs.
fn timeless(rounds: &[adapt::RoundReport]) -> Vec<adapt::RoundReport> {
    rounds.iter().map(|r| adapt::RoundReport { seconds: 0.0, ..r.clone() }).collect()
}

/// A run stopped after round 2 of 3 resumes from its snapshot with round 3 only, and ends where
/// an uninterrupted run ends (round 3 trains no backbone, so Adam's restart cannot show);
/// another run's snapshot is refused.
#[test]
fn an_interrupted_adaptation_resumes_where_it_stopped() {
    let source = random_model("resume");
    let scratch = support::Scratch::new("adapt-resume-work");
    let work = scratch.path().join(".adapted.rounds");
    let three = AdaptConfig { max_rounds: 3, patience: 5, ..config(-1.0) };
    let images = images(6);
    let whole = adapt::adapt(&source, &images, &three, &mut go).unwrap();
    assert_eq!(whole.resumed_after, None);

    let stopped = adapt::adapt_resumable(&source, &images, &three, &work, &mut |e| match e {
        Event::Round(r) if r.round == 2 => ControlFlow::Break(()),
        _ => ControlFlow::Continue(()),
    });
    assert_eq!(stopped.err(), Some(EngineError::Cancelled));
    let mut events = Vec::new();
    let resumed = adapt::adapt_resumable(&source, &images, &three, &work, &mut |e| {
        match e {
            Event::Resumed { rounds } => events.push(format!("resumed {rounds}")),
            Event::Round(r) => events.push(format!("round {}", r.round)),
            Event::Step { round, .. } => assert_eq!(round, 3, "a restored round ran again"),
            Event::TargetCheck { .. } => events.push("check".into()),
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(events, ["resumed 2", "round 3"]);
    assert_eq!(resumed.resumed_after, Some(2));
    assert_eq!(timeless(&resumed.rounds), timeless(&whole.rounds));
    assert_eq!(resumed.backbone_steps, whole.backbone_steps);
    assert!(same(&snapshot(&resumed.vs), &snapshot(&whole.vs)), "the backbone differs from an uninterrupted run's");
    assert!(resumed.neural_mesh.vertex_features.equal(&whole.neural_mesh.vertex_features));
    assert_eq!(resumed.pseudo_poses, whole.pseudo_poses);

    let other = AdaptConfig { seed: 1, ..three };
    let refused = adapt::adapt_resumable(&source, &images, &other, &work, &mut go);
    assert!(matches!(refused, Err(EngineError::InvalidInput(m)) if m.contains("another run")));
}

/// The oracle resumes after its first pass and still takes exactly its budget.
#[test]
fn an_interrupted_oracle_resumes_with_its_budget() {
    let source = random_model("oracle-resume");
    let scratch = support::Scratch::new("oracle-resume-work");
    let work = scratch.path().join(".oracle.rounds");
    let images = images(5);
    let run = |progress: &mut dyn FnMut(Event) -> ControlFlow<()>| {
        adapt::finetune_resumable(&source, &images, &labels(5), Budget::Steps(5), &config(0.8), &work, progress)
    };
    let stopped =
        run(&mut |e| if matches!(e, Event::Round(_)) { ControlFlow::Break(()) } else { ControlFlow::Continue(()) });
    assert_eq!(stopped.err(), Some(EngineError::Cancelled));
    let mut resumed_at = None;
    let tuned = run(&mut |e| {
        if let Event::Resumed { rounds } = e {
            resumed_at = Some(rounds);
        }
        ControlFlow::Continue(())
    })
    .unwrap();
    assert_eq!(resumed_at, Some(1));
    assert_eq!((tuned.backbone_steps, tuned.rounds.len(), tuned.resumed_after), (5, 3, Some(1)));
    assert!(!tuned.neural_mesh.vertex_features.equal(&source.neural_mesh.vertex_features), "C trains with labels");
}
