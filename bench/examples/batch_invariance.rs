//! Whether libtorch's CPU backbone gives a crop the same features whatever it is batched with,
//! and what the differences do to the answers: the measurement behind
//! `engine::backbone::invariant` (a batch of one's small convolutions run as a batch of two) and
//! `engine::estimator::Estimator::features` (CPU passes cut at 15)
//! and docs/ARCHITECTURE.md's "Answers are deterministic".
//!
//! ```text
//! cargo run --release -p udapose-bench --example batch_invariance -- models/car DATA source val 60 8 2
//! ```
//!
//! For each image: its features alone (batch 1) against (a) a batch of B at position 0 with
//! the next B−1 images, (b) the same position in a batch of B with other neighbours (fixed
//! shape, other content), (c) a batch of B at position B−1. Prints the largest relative feature
//! difference of each, how many answers move by more than 1e-4 rad and by more than π/6, the
//! runner-up's score gap where one flips, and how much higher a moved answer's loss is on the
//! crop's batch-1 features; then whether passes of 2, 3, 5 and 8 crops give batch B's features
//! bit for bit, and ms per crop at batch 1 and B (backbone only).

use std::path::Path;
use std::time::Instant;

use anyhow::{Context, Result, bail};
use tch::{Device, Tensor};
use udapose_engine::estimator::{self, Features, PoseSolver};
use udapose_engine::input::{self, Rgb8Image};
use udapose_engine::solver::{Scratch, SolverConfig};
use udapose_engine::{Pose, checkpoint};
use udapose_lab::datasets::syncar::SyncarSplit;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let [model, data, domain, split, n, b, threads] = args.as_slice() else {
        bail!("usage: batch_invariance MODEL DATA DOMAIN SPLIT IMAGES BATCH TORCH_THREADS");
    };
    let threads: i32 = threads.parse().context("TORCH_THREADS")?;
    let (n, b): (usize, usize) = (n.parse().context("IMAGES")?, b.parse().context("BATCH")?);
    tch::set_num_threads(threads);
    let model = checkpoint::load(Path::new(model), Device::Cpu)?;
    let split = SyncarSplit::open(Path::new(data), domain, split)?;
    let images: Vec<Tensor> = (0..n.min(split.len()))
        .map(|i| {
            // Cut at the model's crop size as the service does (the quick set's images are smaller).
            let path = &split.load(i)?.entry.image_path;
            let img = image::open(path).with_context(|| format!("decoding {}", path.display()))?.into_rgb8();
            let (w, h) = (img.width() as usize, img.height() as usize);
            Ok(input::crop(&Rgb8Image::new(img.as_raw(), w, h)?, None, model.manifest.crop)?.tensor())
        })
        .collect::<Result<_>>()?;
    let n = images.len();
    let batch = |idx: &[usize]| -> Result<Vec<Features>> {
        let x = Tensor::cat(&idx.iter().map(|&i| images[i].shallow_clone()).collect::<Vec<_>>(), 0);
        Ok(estimator::features(&model.backbone, &x)?)
    };
    let solver = PoseSolver::for_neural_mesh(&model.neural_mesh, model.manifest.crop, SolverConfig::default())?;
    let mut rows = [
        Row::new("batch B, position 0"),
        Row::new("batch B, position 0, other neighbours"),
        Row::new("batch B, position B-1"),
    ];
    let (mut t1, mut tb) = (0.0, 0.0);
    let mut same = [0usize; 2];
    let mut sizes = [0usize; 4];
    for i in 0..n {
        let t = Instant::now();
        let alone = batch(&[i])?.pop().context("features")?;
        t1 += t.elapsed().as_secs_f64();
        let reference = solver.solve(&alone)?;
        let next: Vec<usize> = (1..b).map(|k| (i + k) % n).collect();
        let other: Vec<usize> = (1..b).map(|k| (i + n / 2 + k) % n).collect();
        let t = Instant::now();
        let first = batch(&[&[i][..], &next].concat())?.swap_remove(0);
        tb += t.elapsed().as_secs_f64() / b as f64;
        let second = batch(&[&[i][..], &other].concat())?.swap_remove(0);
        let last = batch(&[&next[..], &[i][..]].concat())?.pop().context("features")?;
        for (k, size) in [2, 3, 5, 8].into_iter().enumerate() {
            let other_size = batch(&[&[i][..], &next[..size.min(b) - 1]].concat())?.swap_remove(0);
            sizes[k] += usize::from(other_size.data == first.data);
        }
        same[0] += usize::from(first.data == second.data);
        same[1] += usize::from(first.data == last.data);
        // How much worse a moved answer is by the loss on the crop's own (batch 1) features.
        let problem = solver.problem(&alone)?;
        let mut scratch = Scratch::default();
        let reference_loss = problem.loss(&mut scratch, &reference.pose)?;
        for (row, f) in rows.iter_mut().zip([&first, &second, &last]) {
            let pose = solver.solve(f)?.pose;
            let worse = problem.loss(&mut scratch, &pose)? - reference_loss;
            row.add(&alone, f, &reference.pose, &pose, &reference, worse);
        }
    }
    println!("{n} images of {domain}, batch B = {b}, {threads} torch threads");
    for row in &rows {
        row.print(n);
    }
    println!(
        "in a batch of {b}: features bit-identical with other neighbours {}/{n}, at another position {}/{n}",
        same[0], same[1]
    );
    println!(
        "features bit-identical to batch {b}'s: at batch 2 {}/{n}, 3 {}/{n}, 5 {}/{n}, 8 {}/{n}",
        sizes[0], sizes[1], sizes[2], sizes[3]
    );
    println!("ms per crop: batch 1 {:.1}, batch {b} {:.1} ({:.2}x)", 1e3 * t1 / n as f64, 1e3 * tb / n as f64, tb / t1);
    Ok(())
}

struct Row {
    name: &'static str,
    max_rel: f64,
    identical: usize,
    moved: usize,
    max_move: f64,
    /// The largest loss increase of a moved answer, on the batch-1 features.
    max_worse: f64,
    flipped: Vec<f64>,
}

impl Row {
    fn new(name: &'static str) -> Self {
        Row { name, max_rel: 0.0, identical: 0, moved: 0, max_move: 0.0, max_worse: 0.0, flipped: Vec::new() }
    }

    fn add(
        &mut self,
        alone: &Features,
        f: &Features,
        p0: &Pose,
        p: &Pose,
        reference: &udapose_engine::solver::Estimate,
        worse: f64,
    ) {
        let norm = alone.data.iter().map(|v| v.abs()).fold(0f32, f32::max) as f64;
        let diff = alone.data.iter().zip(&f.data).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max) as f64;
        self.max_rel = self.max_rel.max(diff / norm);
        self.identical += usize::from(alone.data == f.data);
        let d =
            udapose_engine::pose_error(Some([p.azimuth, p.elevation, p.theta]), [p0.azimuth, p0.elevation, p0.theta]);
        if d > 1e-4 {
            self.moved += 1;
            self.max_worse = self.max_worse.max(worse);
        }
        if d <= std::f64::consts::PI / 6.0 {
            self.max_move = self.max_move.max(d);
        }
        if d > std::f64::consts::PI / 6.0 {
            let h = &reference.hypotheses;
            self.flipped.push(h.get(1).map_or(f64::NAN, |r| r.loss - h[0].loss));
        }
    }

    fn print(&self, n: usize) {
        println!(
            "{:>40}: features identical {}/{n}, max relative difference {:.2e}; answers moved > 1e-4 rad {} (at most {:.2e} rad below π/6; loss at most {:.1e} higher on the batch-1 features), > π/6 {} (runner-up loss gaps {:?})",
            self.name,
            self.identical,
            self.max_rel,
            self.moved,
            self.max_move,
            self.max_worse,
            self.flipped.len(),
            self.flipped.iter().map(|g| format!("{g:.4}")).collect::<Vec<_>>()
        );
    }
}
