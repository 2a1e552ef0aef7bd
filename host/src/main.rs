//! `deform`: parse the command line, dispatch to [`deform_host::commands`], report errors.

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use deform_host::commands;

/// Real-time soft-tissue deformation: builds the spring-network stiffness matrix K of a tissue
/// grid, encodes it as MVU instruction words and solves K·l = f by conjugate gradients.
#[derive(Debug, Parser)]
#[command(name = "deform", version, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// One variant per subcommand, each wrapping that subcommand's `Args` from `commands::*`.
#[derive(Debug, Subcommand)]
enum Command {
    /// Build the tissue model from the model flags and print the properties of its stiffness
    /// matrix K (size, sparsity, bandwidth, symmetry) and of its instruction-word encoding.
    Model(commands::model::ModelCommandArgs),
    /// Solve the model for the displacements of every node, on the QEMU soft core (default), a
    /// real board (--port) or the host's f64 reference (--target host).
    Solve(commands::solve::SolveArgs),
    /// Quasi-static time steps: loads ramped over --steps steps, K resident on the target,
    /// warm starts, optional displacement-dependent springs (--alpha); per-step CSV and VTK.
    Simulate(commands::simulate::SimulateArgs),
    /// Measure cycles per CG iteration, MFLOPS, convergence, the real-time budget and the
    /// host baseline against the thesis's figures; JSON, CSV and SVG/PNG plots in --out.
    Bench(commands::bench::BenchArgs),
    // Observe and Estimate take their help from their Args' doc comments (which document the
    // observation file format).
    Observe(commands::observe::ObserveArgs),
    Estimate(commands::estimate::EstimateArgs),
    /// Upload a firmware ELF through the target's serial loader (a board on --port, or QEMU
    /// booted with the loader), verify it by CRC in target RAM, start it and confirm it answers.
    Flash(commands::flash::FlashArgs),
    /// The real-time loop: a tool (the scenario's prescribed nodes along their keyframes)
    /// pushes the tissue frame by frame; K stays resident, each frame sends only the tool's
    /// displacements and gets the reaction force back, force queries between frames come
    /// from a local linear model, the field comes quantised at a lower rate (--headless).
    Live(commands::live::LiveArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match &cli.command {
        Command::Model(args) => commands::model::run(args),
        Command::Solve(args) => commands::solve::run(args),
        Command::Simulate(args) => commands::simulate::run(args),
        Command::Bench(args) => commands::bench::run(args).map(|_| ()),
        Command::Observe(args) => commands::observe::run(args),
        Command::Estimate(args) => commands::estimate::run(args),
        Command::Flash(args) => commands::flash::run(args),
        Command::Live(args) => commands::live::run(args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(error) => {
            eprintln!("error: {}", error_chain(&error));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes, `: `-separated like anyhow's `{:#}`, but without a cause that the
/// text before it already ends with: many typed errors name their source in their own message
/// (so that `to_string()` alone is complete), and printing it again would say it twice.
fn error_chain(error: &anyhow::Error) -> String {
    let mut text = error.to_string();
    for cause in error.chain().skip(1) {
        let cause = cause.to_string();
        if !text.ends_with(&cause) {
            text.push_str(": ");
            text.push_str(&cause);
        }
    }
    text
}

#[cfg(test)]
mod tests {
    use super::error_chain;

    #[derive(Debug, thiserror::Error)]
    #[error("cannot read f.elf: {source}")]
    struct Read {
        #[source]
        source: std::io::Error,
    }

    #[test]
    fn a_cause_already_in_the_message_is_not_repeated() {
        let io = std::io::Error::new(std::io::ErrorKind::NotFound, "no such file");
        let error = anyhow::Error::new(Read { source: io }).context("reading the firmware");
        assert_eq!(
            error_chain(&error),
            "reading the firmware: cannot read f.elf: no such file"
        );
        let plain = anyhow::anyhow!("inner").context("outer");
        assert_eq!(error_chain(&plain), "outer: inner");
    }
}
