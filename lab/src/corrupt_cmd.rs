//! `udapose-lab corrupt`: applies one corruption to one image (the parity harness
//! `lab/scripts/corruption_parity.py` drives it).

use std::path::PathBuf;

use anyhow::Context;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use udapose_lab::corruptions::Corruption;

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
    /// Output image; the format follows the extension (use .png for lossless).
    #[arg(long = "out")]
    output: PathBuf,
}

pub fn run(args: &Args) -> anyhow::Result<()> {
    let corruption: Corruption = args.name.parse()?;
    let image = image::open(&args.input).with_context(|| format!("reading {}", args.input.display()))?.to_rgb8();
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    let corrupted = corruption.apply(&image, args.severity, &mut rng)?;
    corrupted.save(&args.output).with_context(|| format!("writing {}", args.output.display()))?;
    Ok(())
}
