//! `udapose-lab`: offline tools around the engine.

mod corrupt_cmd;
mod doctor;
mod synth_cmd;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "udapose-lab",
    version,
    about = "udapose offline tools: environment checks, the SynCar-OOD benchmark, corruptions"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Print the torch version, compute device, thread counts and which assets are available.
    Doctor(doctor::Args),
    /// Apply one ImageNet-C corruption (severity 1-5, seeded) to an image.
    Corrupt(corrupt_cmd::Args),
    /// Render the SynCar-OOD benchmark (every domain and split), or preview sheets of it.
    Synth(synth_cmd::Args),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Doctor(args) => doctor::run(&args),
        Command::Corrupt(args) => corrupt_cmd::run(&args),
        Command::Synth(args) => synth_cmd::run(&args),
    }
}
