//! `udapose-lab`: offline tools around the engine.

mod adapt_cmd;
mod compare_cmd;
mod corrupt_cmd;
mod doctor;
mod eval_cmd;
mod plot;
mod report_cmd;
mod route_cmd;
mod synth_cmd;
mod target_check_cmd;
mod train_cmd;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "udapose-lab",
    version,
    about = "udapose offline tools: environment checks, the SynCar-OOD benchmark, corruptions, source training, adaptation, evaluation"
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
    /// Train the source model (NeMo) on a SynCar-OOD dataset; resumable.
    Train(train_cmd::Args),
    /// Evaluate a model on every domain of a dataset: Acc@π/6, Acc@π/18, MedErr.
    Eval(eval_cmd::Args),
    /// Adapt a model to the images of a folder without labels (3DUDA).
    Adapt(adapt_cmd::AdaptArgs),
    /// The oracle: fine-tune a model with the labels of a split, with a given budget.
    Finetune(adapt_cmd::FinetuneArgs),
    /// The SynCar-OOD report: source, adapted, oracle and ablation per domain (cached stages).
    Report(report_cmd::Args),
    /// Source models side by side: accuracy from their eval reports, size, τ_r, fired ratios and
    /// costs measured in one run → reports/source-models.json and .md.
    Compare(compare_cmd::Args),
    /// Route each test image to the domain whose adapt images it resembles, by image statistics
    /// alone (per-domain experts' probe) → a confusion table.
    Route(route_cmd::Args),
    /// What the service's target check reads for a model: the share of vertices that fire on
    /// images of no object and on each domain's first adapt images.
    TargetCheck(target_check_cmd::Args),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Command::Doctor(args) => doctor::run(&args),
        Command::Corrupt(args) => corrupt_cmd::run(&args),
        Command::Synth(args) => synth_cmd::run(&args),
        Command::Train(args) => train_cmd::run(&args),
        Command::Eval(args) => eval_cmd::run(&args),
        Command::Adapt(args) => adapt_cmd::run_adapt(&args),
        Command::Finetune(args) => adapt_cmd::run_finetune(&args),
        Command::Report(args) => report_cmd::run(&args),
        Command::Compare(args) => compare_cmd::run(&args),
        Command::Route(args) => route_cmd::run(&args),
        Command::TargetCheck(args) => target_check_cmd::run(&args),
    }
}
