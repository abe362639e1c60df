//! The estimator's batching contract: a crop's features (and so its answer) do not depend on
//! what shares its backbone pass, and the answer says how ambiguous it is.

mod support;

use udapose_engine::Pose;
use udapose_engine::estimator::{Estimator, Features};
use udapose_engine::input::{CropBox, Rgb8Image, crop};
use udapose_engine::solver::{Estimate, Hypothesis, SolverConfig};

fn crops(n: usize) -> Vec<udapose_engine::input::Crop> {
    (0..n)
        .map(|k| {
            let raw: Vec<u8> = (0..160 * 64 * 3).map(|i| ((i * (37 + 2 * k) + 11 * k) % 251) as u8).collect();
            crop(
                &Rgb8Image::new(&raw, 160, 64).unwrap(),
                Some(CropBox { x0: 0.0, y0: 0.0, x1: 160.0, y1: 64.0 }),
                [64, 160],
            )
            .unwrap()
        })
        .collect()
}

fn same(a: &Features, b: &Features) -> bool {
    a.data.len() == b.data.len() && a.data.iter().zip(&b.data).all(|(x, y)| x.to_bits() == y.to_bits())
}

#[test]
fn a_crops_features_do_not_depend_on_what_shares_its_pass() {
    let estimator = Estimator::new(support::random_model(3, [64, 160], "batching"), SolverConfig::default()).unwrap();
    let crops = crops(11);
    let all: Vec<_> = crops.iter().collect();
    let lone = estimator.features(&all[..1], 8).unwrap();
    // A batch of one takes the same kernels as any other (backbone::invariant).
    assert!(same(&lone[0], &estimator.features(&all[..1], 1).unwrap()[0]));
    // A pass of 8 then one of 3, and the crop at another place among other neighbours.
    let together = estimator.features(&all, 8).unwrap();
    let elsewhere = estimator.features(&[all[5], all[9], all[0]], 8).unwrap();
    assert_eq!(together.len(), 11);
    assert!(same(&lone[0], &together[0]), "a lone crop differs from the crop in a pass of 8");
    assert!(same(&lone[0], &elsewhere[2]), "the crop's features moved with its neighbours or its place");
    assert!(same(&together[9], &elsewhere[1]), "the second pass's crop differs from the same crop elsewhere");
    // Passes are cut at 15 crops on the CPU, however large max_batch is.
    let wide = estimator.features(&all, 256).unwrap();
    assert!(wide.iter().zip(&together).all(|(a, b)| same(a, b)));
    // max_batch 1: every crop alone, the same answer each time.
    let alone = estimator.features(&all[..2], 1).unwrap();
    assert!(same(&alone[0], &estimator.features(&all[..1], 1).unwrap()[0]));
}

fn hypothesis(azimuth_deg: f64, loss: f64) -> Hypothesis {
    let pose = Pose { azimuth: azimuth_deg.to_radians(), elevation: 0.2, theta: 0.0, distance: 5.0 };
    Hypothesis { pose, loss, init: pose, init_loss: loss, evaluations: 1 }
}

#[test]
fn the_runner_up_gap_is_the_lead_over_the_best_distant_hypothesis() {
    let estimate = |h: Vec<Hypothesis>| Estimate { pose: h[0].pose, score: 1.0 - h[0].loss, hypotheses: h };
    let sep = 30f64.to_radians();
    // 10° away does not count; the flip at 180° does, and the one after it is not the best.
    let e =
        estimate(vec![hypothesis(0.0, 0.20), hypothesis(10.0, 0.21), hypothesis(180.0, 0.25), hypothesis(90.0, 0.4)]);
    assert!((e.runner_up_gap(sep).unwrap() - 0.05).abs() < 1e-12);
    assert_eq!(estimate(vec![hypothesis(0.0, 0.2), hypothesis(20.0, 0.3)]).runner_up_gap(sep), None);
    assert_eq!(estimate(vec![hypothesis(0.0, 0.2)]).runner_up_gap(sep), None);
}

#[test]
fn crops_solved_in_parallel_get_the_answers_they_get_one_by_one() {
    let estimator = Estimator::new(support::random_model(4, [64, 160], "parallel"), SolverConfig::default()).unwrap();
    let crops = crops(5);
    let all: Vec<_> = crops.iter().collect();
    let features = estimator.features(&all, 8).unwrap();
    let together = estimator.estimate_all(&all, &features);
    for ((crop, f), got) in all.iter().zip(&features).zip(together) {
        let (got, ms) = got.unwrap();
        assert_eq!(got.estimate, estimator.estimate_features(crop, f).unwrap().estimate);
        assert!(ms >= 0.0);
    }
    assert!(estimator.estimate_all(&all, &features[..2]).iter().all(Result::is_err), "a count mismatch is an error");
}
