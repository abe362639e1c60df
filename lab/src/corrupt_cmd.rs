//! `udapose-lab corrupt`: applies one corruption to one image (the parity harness
//! `lab/scripts/corruption_parity.py` drives it).

use std::path::PathBuf;

use anyhow::Context;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use udapose_lab::corruptions::{Corruption, CorruptionError};

#[derive(clap::Args)]
pub struct Args {
    /// Corruption name as in `imagecorruptions` (e.g. gaussian_noise, zoom_blur, snow).
    #[arg(long)]
    name: String,
    /// Severity, 1 to 5.
    #[arg(long)]
    severity: u8,
    /// Seed of the ChaCha8 generator that random corruptions draw from.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Input image (any format the `image` crate reads; converted to RGB).
    #[arg(long = "in")]
    input: PathBuf,
    /// Output image; the format follows the extension (use .png for lossless). `{seed}` in it is
    /// replaced by the seed used.
    #[arg(long = "out")]
    output: String,
    /// Corrupt this many times, with seeds `seed`, `seed + 1`, …; `--out` must then contain
    /// `{seed}`. Saves the process start per draw when sampling many seeds.
    #[arg(long, default_value_t = 1)]
    count: u64,
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    let corruption: Corruption = args.name.parse()?;
    if !(1..=5).contains(&args.severity) {
        return Err(CorruptionError::Severity(args.severity).into());
    }
    let image = image::open(&args.input).with_context(|| format!("reading {}", args.input.display()))?.to_rgb8();
    if args.count > 1 && !args.output.contains("{seed}") {
        anyhow::bail!("--count {} needs `{{seed}}` in --out to name the outputs", args.count);
    }
    for seed in args.seed..args.seed + args.count {
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let corrupted = corruption.apply(&image, args.severity, &mut rng)?;
        let output = args.output.replace("{seed}", &seed.to_string());
        corrupted.save(&output).with_context(|| format!("writing {output}"))?;
    }
    Ok(())
}
