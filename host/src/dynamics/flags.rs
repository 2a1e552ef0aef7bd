//! The flags of `deform simulate --dynamic` and dynamic `deform live` sessions (issue 14,
//! [`crate::dynamics`]), merged over a scenario's `[dynamics]` table, which is merged over the
//! defaults.

use clap::Args;

use crate::dynamics::{Damping, DynamicsSettings, DynamicsSpec, Scheme};
use crate::model::NodeField;

/// Mass per node (kg) when neither a flag nor the scenario gives one.
pub const DEFAULT_MASS: f64 = 0.01;
/// Damper coefficient β (N·s/m) when neither a flag nor the scenario gives one.
pub const DEFAULT_DAMPING: f64 = 0.05;

/// Elastodynamics: masses at the nodes and dampers beside the springs.
#[derive(Debug, Clone, PartialEq, Args)]
pub struct DynamicFlags {
    /// Solve the equations of motion M·a + C·v + K·u = f by implicit time steps (masses and
    /// dampers, thesis eq. 4–7) instead of a quasi-static equilibrium per step. Loads without
    /// keyframes then act in full from t = 0. [default: the scenario's `[simulation] dynamic`]
    #[arg(long)]
    pub dynamic: bool,

    /// Lumped mass per node, kg. [default: the scenario's `[dynamics] mass`, else 0.01]
    #[arg(long, value_name = "M", value_parser = parse_positive)]
    pub mass: Option<f64>,

    /// Damper coefficient β beside every spring, N·s/m: one value, or BX,BY,BZ per direction
    /// like k; 0 is an undamped model (whose energy `--scheme trapezoidal` keeps). [default: the
    /// scenario's `[dynamics] damping`, else 0.05]
    #[arg(long, value_name = "B|BX,BY,BZ", value_parser = parse_damping)]
    pub damping: Option<[f64; 3]>,

    /// Rayleigh damping added to the dampers: C += A·M + B·K.
    #[arg(long, value_name = "A,B", value_parser = parse_rayleigh)]
    pub rayleigh: Option<[f64; 2]>,

    /// Time-stepping scheme: backward-euler (first order, L-stable: the default, like SOFA's)
    /// or trapezoidal (Newmark average acceleration: second order, keeps an undamped model's
    /// energy). [default: the scenario's `[dynamics] scheme`, else backward-euler]
    #[arg(long, value_name = "SCHEME", value_parser = |s: &str| s.parse::<Scheme>())]
    pub scheme: Option<Scheme>,

    /// Dynamic mode: target solves per step at most (mixed-precision refinement to --tol).
    /// [default: 8]
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..))]
    pub max_solves: Option<u32>,
}

impl Default for DynamicFlags {
    /// No flag given: what the scenario's `[dynamics]` says, else the defaults.
    fn default() -> Self {
        Self {
            dynamic: false,
            mass: None,
            damping: None,
            rayleigh: None,
            scheme: None,
            max_solves: None,
        }
    }
}

fn parse_positive(s: &str) -> Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
    if v.is_finite() && v > 0.0 {
        Ok(v)
    } else {
        Err(format!("{v} must be finite and greater than 0"))
    }
}

/// β ≥ 0: an undamped model (β = 0) is what the trapezoidal scheme keeps the energy of.
fn parse_non_negative(s: &str) -> Result<f64, String> {
    let v: f64 = s.trim().parse().map_err(|e| format!("{s:?}: {e}"))?;
    if v.is_finite() && v >= 0.0 {
        Ok(v)
    } else {
        Err(format!("{v} must be finite and not negative"))
    }
}

fn parse_damping(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(parse_non_negative)
        .collect::<Result<_, _>>()?;
    match v[..] {
        [b] => Ok([b; 3]),
        [x, y, z] => Ok([x, y, z]),
        _ => Err("give one β or three (BX,BY,BZ)".into()),
    }
}

fn parse_rayleigh(s: &str) -> Result<[f64; 2], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [a, b] if a.is_finite() && b.is_finite() && a >= 0.0 && b >= 0.0 => Ok([a, b]),
        [_, _] => Err("both coefficients must be finite and not negative".into()),
        _ => Err("expected two numbers A,B".into()),
    }
}

impl DynamicFlags {
    /// The dynamic model, if this run is dynamic (`--dynamic` or the scenario's
    /// `dynamic = true`): flags over `[dynamics]` over the defaults. Dynamic flags without a
    /// dynamic run are refused rather than silently ignored.
    pub fn resolve(
        &self,
        scenario_dynamic: bool,
        settings: Option<&DynamicsSettings>,
    ) -> anyhow::Result<Option<DynamicsSpec>> {
        if !(self.dynamic || scenario_dynamic) {
            if self.mass.is_some()
                || self.damping.is_some()
                || self.rayleigh.is_some()
                || self.scheme.is_some()
                || self.max_solves.is_some()
            {
                anyhow::bail!(
                    "--mass, --damping, --rayleigh, --scheme and --max-solves describe a dynamic \
                     simulation: add --dynamic (or `dynamic = true` under [simulation] in the \
                     scenario)"
                );
            }
            return Ok(None);
        }
        let file = settings.cloned().unwrap_or_default();
        Ok(Some(DynamicsSpec {
            mass: self
                .mass
                .map(NodeField::uniform)
                .or(file.mass)
                .unwrap_or_else(|| NodeField::uniform(DEFAULT_MASS)),
            damping: self
                .damping
                .map(Damping::PerDirection)
                .or(file.damping)
                .unwrap_or(Damping::PerDirection([DEFAULT_DAMPING; 3])),
            rayleigh: self.rayleigh.or(file.rayleigh),
            scheme: self.scheme.or(file.scheme).unwrap_or_default(),
        }))
    }
}
