//! The ceiling of the service benchmark: the backbone alone and the engine alone on the same
//! crops, in this process with the servers stopped.

use std::{path::Path, time::Instant};

use anyhow::Result;
use tch::Tensor;
use udapose_engine::{
    checkpoint,
    estimator::Estimator,
    input::{self, Crop, Rgb8Image},
    solver::SolverConfig,
};

pub(super) struct Ceiling {
    /// Backbone crops per second, one at a time.
    pub(super) batch1: f64,
    /// Backbone crops per second in batches of `max_batch`.
    pub(super) batched: f64,
    /// Backbone + solver images per second, one after the other.
    pub(super) engine: f64,
}

/// The backbone (and the engine) alone on the same crops, on this process's CPU or GPU.
pub(super) fn backbone_ceiling(model_dir: &Path, images: &[Vec<u8>], max_batch: usize) -> Result<Ceiling> {
    let device = udapose_engine::runtime::RuntimeInfo::detect().device();
    let estimator = Estimator::new(checkpoint::load(model_dir, device)?, SolverConfig::default())?;
    let size = estimator.model.manifest.crop;
    let crops: Vec<Crop> = images
        .iter()
        .map(|bytes| -> Result<Crop> {
            let img = image::load_from_memory(bytes)?.into_rgb8();
            let (w, h) = (img.width() as usize, img.height() as usize);
            Ok(input::crop(&Rgb8Image::new(img.as_raw(), w, h)?, None, size)?)
        })
        .collect::<Result<_>>()?;
    let run = |batch: &[&Crop]| {
        let tensors: Vec<Tensor> = batch.iter().map(|c| c.tensor()).collect();
        estimator.batch_features(&Tensor::cat(&tensors, 0))
    };
    run(&[&crops[0]])?; // warm-up
    let rounds = 3;
    let t = Instant::now();
    for _ in 0..rounds {
        for c in &crops {
            run(&[c])?;
        }
    }
    let batch1 = (rounds * crops.len()) as f64 / t.elapsed().as_secs_f64();
    let batch: Vec<&Crop> = crops.iter().cycle().take(max_batch).collect();
    run(&batch)?;
    let t = Instant::now();
    let batches = (rounds * crops.len()).div_ceil(max_batch);
    for _ in 0..batches {
        run(&batch)?;
    }
    let batched = (batches * max_batch) as f64 / t.elapsed().as_secs_f64();
    estimator.estimate(&crops[0])?; // warm-up (the solver's thread pool and buffers)
    let t = Instant::now();
    for _ in 0..rounds {
        crops.iter().try_for_each(|c| estimator.estimate(c).map(drop))?;
    }
    let engine = (rounds * crops.len()) as f64 / t.elapsed().as_secs_f64();
    Ok(Ceiling { batch1, batched, engine })
}
