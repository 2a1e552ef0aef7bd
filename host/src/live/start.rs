//! A live session from a scenario and its options: the tool set-up, which engine solves the
//! frames (quasi-static or dynamic, on a board or on the host), the script of a headless
//! session, and the checks that come before anything starts: an option the chosen engine
//! cannot honour is refused, never ignored.

use std::path::Path;

use anyhow::{bail, Context};
use deform_shared::live::LiveParams;

use super::dynamic::DynamicLive;
use super::engine::Engine;
use super::field::FieldChoice;
use super::link::LiveLink;
use super::quasi_static::{HostEngine, TargetEngine};
use super::resident::{resident_setup, ResidentEngine, ResidentParams};
use super::session::{Script, Timing};
use super::setup::ToolKind;
use super::{LiveSetup, SetupError};
use crate::board::Board;
use crate::dynamics::target::{DynamicModel, DynamicParams};
use crate::dynamics::DynamicsSpec;
use crate::encode::{EncodeOptions, Partition};
use crate::model::Connection;
use crate::scenario::{Scenario, Simulation};

/// A session's options, each `None` where not given (its default then applies, or it does not
/// apply: see [`Options::check`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Options {
    /// Relative residual at which a frame's solve stops. [default: 1e-4]
    pub tol: Option<f64>,
    /// Iterations per frame's solve. [default: 500]
    pub max_iter: Option<u32>,
    /// Hart 0's cycles per frame's solve (0: none). [default: 0]
    pub cycle_budget: Option<u64>,
    /// Target solves per dynamic frame. [default: 8]
    pub max_solves: Option<u32>,
    /// Read the field every this many frames (0: never). [default: 10]
    pub field_every: Option<u32>,
    /// The nodes a field frame carries. [default: all]
    pub field: Option<FieldChoice>,
    /// Local-model queries between frames. [default: 3]
    pub forces_per_frame: Option<u32>,
    /// Frames to run. [default: the scenario's steps]
    pub frames: Option<u32>,
    /// Real time at this frame rate.
    pub pace: Option<f64>,
    /// Seconds one frame's answer may take. [default: 60]
    pub timeout: Option<u64>,
}

/// How a session runs, which decides what its options mean.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Mode {
    pub dynamic: bool,
    pub on_host: bool,
    /// `--serve`: frames come from the browser, not a script.
    pub serve: bool,
}

impl Options {
    pub fn tol(&self) -> f64 {
        self.tol.unwrap_or(1e-4)
    }
    pub fn max_iter(&self) -> u32 {
        self.max_iter.unwrap_or(500)
    }
    pub fn cycle_budget(&self) -> u64 {
        self.cycle_budget.unwrap_or(0)
    }
    pub fn field(&self) -> FieldChoice {
        self.field.unwrap_or_default()
    }
    pub fn timeout(&self) -> std::time::Duration {
        std::time::Duration::from_secs(self.timeout.unwrap_or(60))
    }

    /// Refuses an option `mode`'s engine has no use for, naming it and why.
    pub fn check(&self, mode: Mode) -> anyhow::Result<()> {
        let refuse = |given: bool, flag: &str, why: &str| -> anyhow::Result<()> {
            if given {
                bail!("{flag} {why}");
            }
            Ok(())
        };
        if mode.on_host {
            let why = "applies to a target's solves; --target host solves every frame by the \
                       converged f64 reference";
            refuse(self.tol.is_some(), "--tol", why)?;
            refuse(self.max_iter.is_some(), "--max-iter", why)?;
            refuse(self.cycle_budget.is_some(), "--cycle-budget", why)?;
            refuse(self.max_solves.is_some(), "--max-solves", why)?;
            refuse(self.timeout.is_some(), "--timeout", why)?;
        }
        if mode.dynamic || mode.on_host {
            let why = if mode.dynamic {
                "applies to quasi-static frames; a dynamic frame brings the whole field and has \
                 no local model"
            } else {
                "applies to a target: the host has the whole field and no local model"
            };
            refuse(self.field.is_some(), "--field", why)?;
            refuse(self.field_every.is_some(), "--field-every", why)?;
            refuse(self.forces_per_frame.is_some(), "--forces-per-frame", why)?;
        }
        if mode.dynamic {
            refuse(
                self.cycle_budget.is_some(),
                "--cycle-budget",
                "applies to quasi-static frames; a dynamic frame is refined to --tol (at most \
                 --max-solves target solves of --max-iter iterations)",
            )?;
            refuse(
                self.pace.is_some(),
                "--pace",
                "applies to quasi-static frames; a dynamic session runs every step",
            )?;
        } else {
            refuse(
                self.max_solves.is_some(),
                "--max-solves",
                "applies to dynamic frames (refinement); a quasi-static frame is one solve",
            )?;
        }
        if mode.serve {
            let why = "applies to --headless; with --serve every frame brings the field and \
                       there are no queries between frames";
            refuse(self.field_every.is_some(), "--field-every", why)?;
            refuse(self.forces_per_frame.is_some(), "--forces-per-frame", why)?;
        }
        if self.pace.is_some_and(|hz| !(hz.is_finite() && hz > 0.0)) {
            bail!("--pace must be a positive frame rate");
        }
        Ok(())
    }
}

/// A scenario ready for a live session: its tool set-up and, if dynamic, its dynamic model.
pub struct Live {
    pub scenario: Scenario,
    /// The MVUs the matrix is split over.
    pub mvus: u8,
    pub simulation: Simulation,
    pub setup: LiveSetup,
    pub dynamics: Option<DynamicsSpec>,
}

impl Live {
    /// Loads `path` (with `connection` over its spring model) and sets the tool up, split over
    /// `mvus` MVUs. A tool node the set-up refuses is named with its place in the file.
    pub fn load(
        path: &Path,
        connection: Option<Connection>,
        dynamics: &crate::dynamics::flags::DynamicFlags,
        mvus: u8,
    ) -> anyhow::Result<Self> {
        let mut scenario = Scenario::load(path, None)?;
        if let Some(c) = connection {
            scenario.model.connection = c;
        }
        let Some(simulation) = scenario.simulation.clone() else {
            bail!(
                "{}: no [simulation] table, so no tool path: give [[simulation.displace]] or \
                 [[simulation.load]] keyframes",
                path.display()
            );
        };
        let layout = layout(mvus);
        let setup = LiveSetup::for_simulation(&scenario.model, &simulation, &layout)
            .map_err(|e| located(path, &simulation, e))?;
        let dynamics = dynamics.resolve(simulation.dynamic, scenario.dynamics.as_ref())?;
        if dynamics.is_some() && setup.kind == ToolKind::Force {
            bail!(
                "{}: dynamic frames drive a displacement tool ([[simulation.displace]] \
                 keyframes); a force tool runs quasi-static frames only",
                path.display()
            );
        }
        Ok(Self {
            scenario,
            mvus,
            simulation,
            setup,
            dynamics,
        })
    }

    /// The tool's input at time `t`.
    pub fn tool_at(&self, t: f64) -> Vec<[f64; 3]> {
        self.setup
            .tool_at(&self.scenario.model, &self.simulation, t)
    }

    /// The dynamic model for the scenario's step, built once (on a target, checked against
    /// its fixed point before a board opens).
    pub fn dynamic_model(&self, on_target: bool) -> anyhow::Result<Option<DynamicModel>> {
        let Some(spec) = &self.dynamics else {
            return Ok(None);
        };
        let (model, h) = (&self.setup.model, self.simulation.dt);
        let built = match on_target {
            true => DynamicModel::for_target(model, spec, h),
            false => DynamicModel::new(model, spec, h),
        };
        Ok(Some(built.context("the dynamic model")?))
    }

    /// The engine: on `board` (`None`: the host), dynamic if `built` is given. `checked`:
    /// every frame is held against the f64 reference (the headless session).
    pub fn engine<'a>(
        &'a self,
        board: Option<&'a mut Board>,
        built: Option<DynamicModel>,
        options: &Options,
        checked: bool,
    ) -> anyhow::Result<Box<dyn Engine + 'a>> {
        let (setup, mvus) = (&self.setup, self.mvus);
        Ok(match (board, built) {
            (None, None) => Box::new(HostEngine::new(setup)),
            (None, Some(built)) => Box::new(<DynamicLive>::host(&setup.model, &setup.tools, built)),
            (Some(board), Some(built)) => {
                let resident = ResidentParams {
                    tol: options.tol(),
                    max_iterations: options.max_iter(),
                    cycle_budget: options.cycle_budget(),
                    layout: layout(mvus),
                };
                // The target forms the steps itself where it can; whole vectors otherwise.
                if let Ok(formed) = resident_setup(&setup.model, &setup.tools, &built, &resident) {
                    let target = &mut board.target;
                    return Ok(Box::new(
                        ResidentEngine::start(
                            &setup.model,
                            &setup.tools,
                            built,
                            &formed,
                            target,
                            checked,
                        )
                        .context("setting the dynamic session up on the target")?,
                    ));
                }
                let params = DynamicParams {
                    tol: options.tol(),
                    max_solves: options
                        .max_solves
                        .unwrap_or(crate::refine::DEFAULT_MAX_SOLVES),
                    max_iterations: options.max_iter(),
                    check_reference: true,
                    layout: layout(mvus),
                };
                let target = &mut board.target;
                Box::new(DynamicLive::on_target(
                    &setup.model,
                    &setup.tools,
                    built,
                    params,
                    target,
                )?)
            }
            (Some(board), None) => {
                let params = LiveParams {
                    tolerance: options.tol() as f32,
                    max_iterations: options.max_iter(),
                    cycle_budget: options.cycle_budget(),
                    scale: setup.scale.map(|s| s as f32),
                };
                let link = LiveLink::start(&mut board.target, setup, params)
                    .context("setting the live session up on the target")?;
                Box::new(TargetEngine::new(link, setup, checked))
            }
        })
    }

    /// The line that says what a headless session will run, before its frames.
    pub fn tool_line(
        &self,
        options: &Options,
        script: &Script,
        mode: Mode,
        on: &str,
        mvus: u8,
    ) -> String {
        let (setup, frames) = (&self.setup, script.timing.frames());
        let target = match mode.on_host {
            true => "on the host (the f64 reference)".to_string(),
            false => format!("tolerance {:e}, {mvus} MVU(s), on {on}", options.tol()),
        };
        if mode.dynamic {
            return format!(
                "tool        {} node(s), {frames} frames of {} s; {target}",
                setup.tools.len(),
                self.simulation.dt
            );
        }
        let budget = match mode.on_host {
            true => String::new(),
            false => format!(", budget {} cycles", options.cycle_budget()),
        };
        format!(
            "tool        {} {} node(s), {frames} frames over {} s; {target}{budget}",
            setup.tools.len(),
            setup.kind.name(),
            self.simulation.end_time()
        )
    }

    /// The headless script: the scenario's steps (or `--frames`) over its time span, dynamic
    /// frames one h each, or paced in real time.
    pub fn script(&self, options: &Options) -> Script {
        let sim = &self.simulation;
        let frames = options.frames.unwrap_or(sim.steps);
        let timing = match (options.pace, &self.dynamics) {
            (Some(hz), _) => Timing::Paced {
                hz,
                end: sim.end_time(),
            },
            (None, Some(_)) => Timing::Steps { frames, h: sim.dt },
            (None, None) => Timing::Spread {
                frames,
                end: sim.end_time(),
            },
        };
        Script {
            timing,
            field_every: options.field_every.unwrap_or(10),
            field: options.field(),
            queries_per_frame: options.forces_per_frame.unwrap_or(3),
        }
    }
}

/// The layout live sessions use: rows over `mvus` MVUs, conjugate symmetry where it holds.
pub fn layout(mvus: u8) -> EncodeOptions {
    EncodeOptions {
        mvus,
        partition: Partition::Rows,
        use_symmetry: true,
    }
}

/// A set-up error with the file and line of the schedule that named the node, where it is one.
fn located(path: &Path, simulation: &Simulation, e: SetupError) -> anyhow::Error {
    let node = match &e {
        SetupError::FixedToolNode(n)
        | SetupError::ToolOutsideGrid(n)
        | SetupError::DuplicateToolNode(n) => Some(*n),
        SetupError::RowTooLong { node, .. } => Some(*node),
        _ => None,
    };
    let line = node.and_then(|n| simulation.line_of(n));
    match line {
        Some(line) => anyhow::anyhow!("{}:{line}: {e}", path.display()),
        None => anyhow::anyhow!("{}: {e}", path.display()),
    }
}
