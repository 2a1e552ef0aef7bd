//! `deform observe`: synthetic observation sets for the inverse models (see
//! [`crate::inverse::synthetic`]) — the model's forward solution plus white noise, written in
//! the observation CSV format that `deform estimate` reads.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use crate::inverse::synthetic::{forward, forward_displacement_dependent, observe, Noise};
use crate::inverse::Observations;
use crate::model::flags::ModelFlags;
use crate::model::Model;
use crate::output::file::write_atomic;
use crate::output::paths::Outputs;
use crate::reference::max_abs;
use crate::scenario::resolve_model;
use crate::simulate::plan::parse_alpha;

/// Write observation sets: the model's displacements (solved by the f64 reference) plus white
/// noise, one CSV row per node per set.
///
/// The file has the header `set,i,j,k,ux,uy,uz,fx,fy,fz`: the set number, the node's grid
/// indices, its displacement and the load applied to it. Real measurements can be brought to
/// `deform estimate` in the same format (every set must list every node of the grid).
#[derive(Debug, Clone, Args)]
pub struct ObserveArgs {
    /// A scenario file (TOML, see examples/) giving the true tissue (e.g. a stiff inclusion)
    /// and its loads. Flags given on the command line override it.
    #[arg(value_name = "SCENARIO.toml")]
    pub scenario: Option<PathBuf>,

    #[command(flatten)]
    pub model: ModelFlags,

    /// The CSV file to write.
    #[arg(long, value_name = "FILE.csv")]
    pub out: PathBuf,

    /// Observation sets (repeated measurements of the same loading).
    #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u64).range(1..))]
    pub sets: u64,

    /// Variance of the white noise added to every displacement component. [default: 0]
    #[arg(long, value_name = "VAR", default_value_t = 0.0, value_parser = parse_variance, allow_hyphen_values = true)]
    pub noise_u: f64,

    /// Variance of the white noise added to every load component (at every node, loaded or
    /// not). [default: 0]
    #[arg(long, value_name = "VAR", default_value_t = 0.0, value_parser = parse_variance, allow_hyphen_values = true)]
    pub noise_f: f64,

    /// Seed of the noise generator: the same seed gives the same file.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,

    /// Displacement-dependent springs k̃ = a0 + a1·ΣΔl + a2·ΣΔl² (thesis 3.2.2) as the truth,
    /// for `deform estimate --parametric`. Default: the model's linear springs.
    #[arg(long, value_name = "A0,A1,A2", value_parser = parse_alpha, allow_hyphen_values = true)]
    pub alpha: Option<[f64; 3]>,

    /// Add the new sets to the existing FILE.csv (numbered after its highest set) instead of
    /// replacing it: several load cases in one file, one `observe --append` per case.
    #[arg(long)]
    pub append: bool,
}

fn parse_variance(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        Ok(_) => Err("a variance must be finite and non-negative".into()),
        Err(e) => Err(format!("not a number: {e}")),
    }
}

pub fn run(args: &ObserveArgs) -> anyhow::Result<()> {
    // (--append reads the file it writes on purpose: it is not counted as an input.)
    Outputs::new()
        .input("scenario", args.scenario.as_deref())
        .file("--out", Some(&args.out))
        .check()?;
    let (_, spec) = resolve_model(args.scenario.as_deref(), &args.model)?;
    let model = Model::build(&spec).context("building the model")?;
    let mut existing = if args.append && args.out.exists() {
        Observations::read(&args.out, model.grid())
            .context("reading the file to append to (--append)")?
            .sets
    } else {
        Vec::new()
    };
    let first = existing.last().map_or(0, |s| s.id + 1);
    let truth = match args.alpha {
        None => forward(&model),
        Some(alpha) => forward_displacement_dependent(&model, alpha),
    }
    .context("solving the forward model")?;
    let sets = usize::try_from(args.sets).context("--sets is too large")?;
    let noise = Noise {
        displacement_variance: args.noise_u,
        load_variance: args.noise_f,
        seed: args.seed,
    };
    let new = observe(&model, &truth, sets, first, noise)?;
    let count = new.sets.len();
    existing.extend(new.sets);
    let all = Observations {
        grid: model.grid(),
        sets: existing,
    };
    write_atomic(&args.out, |out| Ok(all.write(out)?))?;
    match args.alpha {
        None => println!("model       {}", spec.describe()),
        Some([a0, a1, a2]) => println!(
            "model       {} grid, {}, springs k̃ = {a0} + {a1}·ΣΔl + {a2}·ΣΔl²",
            spec.grid, spec.connection
        ),
    }
    println!(
        "truth       max |u| = {:.6e} (f64 reference)",
        truth.iter().map(|u| max_abs(u)).fold(0.0, f64::max)
    );
    println!(
        "noise       variance {:e} on displacements, {:e} on loads, seed {}",
        args.noise_u, args.noise_f, args.seed
    );
    println!(
        "wrote       {} set(s) ({}..={}) × {} nodes to {}{}",
        count,
        first,
        first + count as u64 - 1,
        model.n(),
        args.out.display(),
        if first > 0 {
            format!(" ({} sets in all)", all.sets.len())
        } else {
            String::new()
        }
    );
    Ok(())
}
