//! What a time series runs, once a scenario file, the flags and the defaults are merged: the
//! static model, the schedule, the displacement-dependent springs and the dynamic model if the
//! run is dynamic. `deform simulate` builds it from its flags; the HIL tests from a file.

use std::path::Path;

use anyhow::bail;

use super::{Nonlinear, Schedule};
use crate::dynamics::flags::DynamicFlags;
use crate::dynamics::DynamicsSpec;
use crate::model::flags::ModelFlags;
use crate::model::{Model, ModelError, ModelSpec};
use crate::scenario::Simulation;

/// The flags of a series, each `None` where the scenario or the default decides.
#[derive(Debug, Clone, Default)]
pub struct Overrides {
    pub model: ModelFlags,
    pub steps: Option<u32>,
    pub dt: Option<f64>,
    pub alpha: Option<[f64; 3]>,
    pub dynamics: DynamicFlags,
}

/// A series' inputs once flags, scenario file and defaults are merged.
pub struct SeriesPlan {
    /// The static model (a scenario's schedules at their final time).
    pub spec: ModelSpec,
    pub schedule: Schedule,
    pub nonlinear: Option<Nonlinear>,
    /// The scenario's `[simulation]`, whose keyframes drive the steps.
    pub simulation: Option<Simulation>,
    /// Masses and dampers, if the run is dynamic.
    pub dynamics: Option<DynamicsSpec>,
}

impl SeriesPlan {
    /// Reads the scenario file at `path`, if any, and merges `flags` over it.
    pub fn load(path: Option<&Path>, flags: &Overrides) -> anyhow::Result<Self> {
        let (scenario, spec) = crate::scenario::resolve_model(path, &flags.model)?;
        let dynamics = flags.dynamics.resolve(
            scenario
                .as_ref()
                .and_then(|s| s.simulation.as_ref())
                .is_some_and(|s| s.dynamic),
            scenario.as_ref().and_then(|s| s.dynamics.as_ref()),
        )?;
        let simulation = scenario.and_then(|s| s.simulation);
        let schedule = Schedule {
            steps: flags
                .steps
                .or(simulation.as_ref().map(|s| s.steps))
                .unwrap_or(10),
            dt: flags
                .dt
                .or(simulation.as_ref().map(|s| s.dt))
                .unwrap_or(0.1),
        };
        if !(schedule.dt.is_finite() && schedule.dt > 0.0) {
            bail!(
                "--dt {}: the time step must be finite and greater than 0",
                schedule.dt
            );
        }
        let nonlinear = flags
            .alpha
            .or(simulation
                .as_ref()
                .and_then(|s| s.nonlinear.as_ref().map(|n| n.alpha)))
            .map(|alpha| Nonlinear { alpha });
        if dynamics.is_some() && nonlinear.is_some() {
            bail!(
                "the displacement-dependent springs (--alpha) are not supported with --dynamic yet"
            );
        }
        Ok(Self {
            spec,
            schedule,
            nonlinear,
            simulation,
            dynamics,
        })
    }

    /// The model at time `t`: the keyframes evaluated at t, or the static model.
    pub fn model_at(&self, t: f64) -> Result<Model, ModelError> {
        match &self.simulation {
            Some(sim) => Model::build(&sim.spec_at(&self.spec, t)),
            None => Model::build(&self.spec),
        }
    }
}

/// `A0,A1,A2` for `--alpha` (`deform simulate`'s and `deform observe`'s).
pub fn parse_alpha(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>().map_err(|e| format!("{p:?}: {e}")))
        .collect::<Result<_, _>>()?;
    let a: [f64; 3] = v
        .try_into()
        .map_err(|_| "expected three numbers a0,a1,a2".to_string())?;
    if a.iter().all(|x| x.is_finite()) && a[0] > 0.0 {
        Ok(a)
    } else {
        Err("a0 must be positive and all three finite".into())
    }
}
