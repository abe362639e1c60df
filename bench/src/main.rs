//! `udapose-bench`: benchmarks on real data. `solver` times udapose's solver against the
//! autograd reference, `service` the inference service under load, `gate` checks the label-free
//! validation gate against the true accuracy change, and `scale` measures scale-out on one
//! machine. Each writes a JSON report and its Markdown twin under `reports/`.

mod bad_inputs;
mod continual;
mod gate;
mod harness;
mod input;
mod paired;
mod scale;
mod service;
mod solver;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(
    name = "udapose-bench",
    version,
    about = "udapose benchmarks on real data: the solver against the autograd reference, the service under load, the validation gate, scale-out"
)]
struct Cli {
    #[command(subcommand)]
    command: Bench,
}

#[derive(Subcommand)]
enum Bench {
    /// udapose's solver vs the autograd reference (NeMo's way) on the same images and features:
    /// time per image, Acc@π/6, and end-to-end latency with the backbone's share.
    Solver(solver::SolverArgs),
    /// The inference service under load: throughput and p50/p99 latency at several client
    /// concurrencies, batching on and off, against the backbone-only ceiling.
    Service(service::ServiceArgs),
    /// The label-free validation gate on SynCar-OOD: source vs. adapted model per domain on the
    /// held-out adapt images, and whether each decision agrees with the true accuracy change.
    Gate(gate::GateArgs),
    /// Scale-out on one machine: serve replicas and an adapt worker on an S3-compatible store;
    /// throughput with 1, 2 and 3 replicas, failed requests under faults (kill -9 of a replica
    /// or of the worker mid-job, swaps, a rollback), and the swap propagation time.
    Scale(scale::ScaleArgs),
    /// Every bad input of the hostile-user review over HTTP and gRPC: status, message, panics
    /// and health after each (reports/bad-inputs.md); fails unless every row is as specified.
    BadInputs(bad_inputs::BadInputsArgs),
    /// What an estimate's input costs against one backbone pass: JPEG decoding at full and
    /// reduced size and cropping (320×128, 1280×512, 4000×3000), and requests with 1, 4, 16 boxes.
    Input(input::InputArgs),
    /// Online adaptation over a sequence of domains through real servers: after each job,
    /// Acc@π/6 on every domain of the sequence, the gate's verdict, and the job's time; rows
    /// with no adaptation, each job judged alone, and the gate guarding earlier domains.
    Continual(continual::ContinualArgs),
}

fn main() -> anyhow::Result<()> {
    match Cli::parse().command {
        Bench::Solver(a) => solver::run(&a),
        Bench::BadInputs(a) => bad_inputs::run(&a),
        Bench::Service(a) => service::run(&a),
        Bench::Gate(a) => gate::run(&a),
        Bench::Scale(a) => scale::run(&a),
        Bench::Input(a) => input::run(&a),
        Bench::Continual(a) => continual::run(&a),
    }
}

#[cfg(test)]
mod tests {
    use clap::CommandFactory;

    /// clap's own checks of every subcommand's arguments (names, defaults, `requires`).
    #[test]
    fn arguments_are_consistent() {
        super::Cli::command().debug_assert();
    }

    #[test]
    fn a_reports_command_line_quotes_what_a_shell_would_split() {
        let q = super::harness::shell_quoted;
        assert_eq!(q("--images"), "--images");
        assert_eq!(q("data/a-b_c.png"), "data/a-b_c.png");
        assert_eq!(q("quick set, 64x160"), "'quick set, 64x160'");
        assert_eq!(q("it's"), "'it'\\''s'");
        assert_eq!(q(""), "''");
    }
}
