//! Scenario files: a whole solve described in TOML, read by `deform solve FILE` and
//! `deform model FILE`. Command-line flags override the file, which overrides the built-in
//! defaults (the thesis 2.6 example); see [`crate::cli_model::ModelFlags`].
//!
//! ```toml
//! grid = [10, 10, 10]          # NX, NY, NZ
//! model = "a"                  # "a" (6 neighbours) or "b" (26)
//!
//! [elasticity]
//! k = [1, 2, 0.5]              # homogeneous: K, or [KX, KY, KZ]
//! # heterogeneous (any of these makes it so; one K for x, y and z):
//! # background = 1.0           # default: k, if k is a single number
//! # inclusion = [{ center = [5, 5, 5], radius = 2.5, k = 5 }]   # node-index units
//! # field = "stiffness.csv"    # rows i,j,k,k; relative to this file; applied last
//!
//! [boundary]
//! fix = ["corners"]            # corners, none, x-, x+, y-, y+, z-, z+ (a union)
//! fix_nodes = [[0, 0, 0]]
//! displace = [{ node = [5, 5, 9], u = [0, 0, -1] }]
//!
//! [loads]
//! point = [{ node = [0, 5, 5], force = [1, 0, 0] }]
//! pressure = [{ face = "z+", force = [0, 0, -1] }]   # total force over the face
//!
//! [solver]
//! tol = 1e-8
//! max_iter = 10000
//! max_solves = 8
//! target = "qemu"              # or "litex", "host"
//! timeout = 300                # seconds per target solve
//!
//! [output]
//! out = "u.csv"                # relative to the current directory, like --out
//!
//! [simulation]                 # for `deform simulate`; see [`simulation`]
//!
//! [dynamics]                   # masses and dampers (dynamic = true); see [`dynamics`]
//! ```
//!
//! `deform solve` and `deform model` solve one static state: the `[boundary]` and `[loads]`
//! tables plus every `[simulation]` schedule evaluated at the final time steps·dt (a scheduled
//! displacement replaces a static one at the same node; scheduled loads add to the static ones).
//!
//! Every error names the file, the line and column, and the key: syntax, unknown keys and wrong
//! types from the TOML parser, semantic errors (a node outside the grid, a bad face name, a
//! non-positive stiffness, unsorted keyframes) from spans kept while parsing.

pub mod dynamics;
pub mod field;
pub mod simulation;

use std::fmt;
use std::ops::Range;
use std::path::{Path, PathBuf};

use serde::Deserialize;
use toml::Spanned;

use crate::model::{
    Connection, Elasticity, FacePressure, FixedNodeSet, Grid, ModelSpec, Node, PointLoad,
    PrescribedDisplacement,
};
pub use dynamics::DynamicsSettings;
pub use field::{read_node_field_csv, Quantity};
use field::{FieldParts, InclusionAt};
pub use simulation::{value_at, Keyframe, NodeSchedule, Nonlinear, Simulation};
use simulation::{ScheduleToml, SimulationToml};

/// A scenario-file error: where, which key, what.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{}:{line}:{column}: {key}: {message}", path.display())]
pub struct ScenarioError {
    pub path: PathBuf,
    /// 1-based.
    pub line: usize,
    /// 1-based, in characters.
    pub column: usize,
    /// The key (with its table, e.g. `boundary.displace`) the error is about.
    pub key: String,
    pub message: String,
}

/// `[solver]`: every field optional (a flag or the built-in default fills it in).
#[derive(Debug, Clone, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SolverSettings {
    pub tol: Option<f64>,
    pub max_iter: Option<u32>,
    pub max_solves: Option<u32>,
    /// `qemu`, `litex` or `host`.
    pub target: Option<crate::board::TargetKind>,
    pub timeout: Option<u64>,
}

/// A loaded scenario file.
#[derive(Debug, Clone, PartialEq)]
pub struct Scenario {
    pub path: PathBuf,
    /// The static state that `deform solve` solves (schedules at the final time applied).
    pub model: ModelSpec,
    pub solver: SolverSettings,
    pub out: Option<PathBuf>,
    pub simulation: Option<Simulation>,
    /// `[dynamics]`: masses and dampers for a dynamic simulation.
    pub dynamics: Option<DynamicsSettings>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FileToml {
    grid: Option<Spanned<[usize; 3]>>,
    model: Option<ModelName>,
    elasticity: Option<ElasticityToml>,
    boundary: Option<BoundaryToml>,
    loads: Option<LoadsToml>,
    solver: Option<Spanned<SolverSettings>>,
    output: Option<OutputToml>,
    simulation: Option<SimulationToml>,
    dynamics: Option<dynamics::DynamicsToml>,
}

#[derive(Debug, Clone, Copy, Deserialize)]
enum ModelName {
    #[serde(rename = "a", alias = "A")]
    A,
    #[serde(rename = "b", alias = "B")]
    B,
}

#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum KToml {
    One(f64),
    Three([f64; 3]),
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ElasticityToml {
    k: Option<Spanned<KToml>>,
    background: Option<Spanned<f64>>,
    #[serde(default)]
    inclusion: Vec<Spanned<InclusionToml>>,
    field: Option<Spanned<String>>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct InclusionToml {
    center: [f64; 3],
    radius: f64,
    k: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct BoundaryToml {
    fix: Option<Vec<Spanned<String>>>,
    #[serde(default)]
    fix_nodes: Vec<Spanned<[usize; 3]>>,
    #[serde(default)]
    displace: Vec<DisplaceToml>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct DisplaceToml {
    node: Spanned<[usize; 3]>,
    u: Spanned<[f64; 3]>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct LoadsToml {
    #[serde(default)]
    point: Vec<PointToml>,
    #[serde(default)]
    pressure: Vec<PressureToml>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PointToml {
    node: Spanned<[usize; 3]>,
    force: Spanned<[f64; 3]>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PressureToml {
    face: Spanned<String>,
    force: Spanned<[f64; 3]>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct OutputToml {
    out: Option<PathBuf>,
}

/// Reads the scenario file at `path`, if any, and merges the model `flags` over it over the
/// defaults: the model every command that builds one starts from.
pub fn resolve_model(
    path: Option<&Path>,
    flags: &crate::model::flags::ModelFlags,
) -> Result<(Option<Scenario>, ModelSpec), ScenarioError> {
    let scenario = match path {
        Some(path) => Some(Scenario::load(path, flags.grid)?),
        None => None,
    };
    let spec = flags.spec_over(scenario.as_ref().map(|s| &s.model));
    Ok((scenario, spec))
}

/// 1-based line and column (in characters) of byte `offset` in `src`.
pub fn line_column(src: &str, offset: usize) -> (usize, usize) {
    let offset = offset.min(src.len());
    let before = &src[..offset];
    let line = before.matches('\n').count() + 1;
    let line_start = before.rfind('\n').map_or(0, |p| p + 1);
    (line, before[line_start..].chars().count() + 1)
}

/// A best guess at the key a parser error at `span` is about: the table header above it plus
/// the key at the span (an unknown key) or the nearest `key =` before it (a bad value).
fn key_at(src: &str, span: &Range<usize>) -> String {
    let start = span.start.min(src.len());
    let before = &src[..start];
    let is_key = |s: &str| {
        !s.is_empty()
            && s.chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
    };
    let at = src.get(span.clone()).unwrap_or("").trim();
    let key = if is_key(at) && !at.chars().all(|c| c.is_ascii_digit() || c == '-') {
        at.to_string()
    } else {
        let eq = before.rfind('=');
        eq.map(|eq| {
            let head = before[..eq].trim_end();
            let from = head
                .rfind(|c: char| !(c.is_ascii_alphanumeric() || c == '_' || c == '-'))
                .map_or(0, |p| p + 1);
            head[from..].to_string()
        })
        .unwrap_or_default()
    };
    let table = before
        .lines()
        .rev()
        .map(str::trim)
        .find(|l| l.starts_with('['))
        .map(|l| l.trim_matches(|c| c == '[' || c == ']').trim().to_string());
    match (table, key.is_empty()) {
        (Some(t), false) => format!("{t}.{key}"),
        (Some(t), true) => t,
        (None, false) => key,
        (None, true) => "(top level)".to_string(),
    }
}

struct Ctx<'a> {
    path: &'a Path,
    src: &'a str,
}

impl Ctx<'_> {
    fn err(&self, span: Range<usize>, key: &str, message: impl fmt::Display) -> ScenarioError {
        let (line, column) = line_column(self.src, span.start);
        ScenarioError {
            path: self.path.to_path_buf(),
            line,
            column,
            key: key.to_string(),
            message: message.to_string(),
        }
    }

    fn node(&self, grid: Grid, s: &Spanned<[usize; 3]>, key: &str) -> Result<Node, ScenarioError> {
        let [i, j, k] = *s.get_ref();
        let node = Node::new(i, j, k);
        if grid.contains(node) {
            Ok(node)
        } else {
            Err(self.err(
                s.span(),
                key,
                format!(
                    "node {node} is outside the {grid} grid (valid indices: i < {}, j < {}, k < {})",
                    grid.nx(),
                    grid.ny(),
                    grid.nz()
                ),
            ))
        }
    }

    fn finite(&self, s: &Spanned<[f64; 3]>, key: &str) -> Result<[f64; 3], ScenarioError> {
        let v = *s.get_ref();
        if v.iter().all(|x| x.is_finite()) {
            Ok(v)
        } else {
            Err(self.err(s.span(), key, "every component must be finite"))
        }
    }
}

impl Scenario {
    /// Reads and checks `path`. `grid_override` (a --grid flag) replaces the file's grid, and
    /// the file's nodes are checked against it.
    pub fn load(path: &Path, grid_override: Option<Grid>) -> Result<Self, ScenarioError> {
        let src = std::fs::read_to_string(path).map_err(|e| ScenarioError {
            path: path.to_path_buf(),
            line: 0,
            column: 0,
            key: "(file)".into(),
            message: format!("cannot read the scenario file: {e}"),
        })?;
        Self::parse(path, &src, grid_override)
    }

    /// Parses `src` as if read from `path` (which names the file in errors and anchors a
    /// relative `field` path).
    pub fn parse(
        path: &Path,
        src: &str,
        grid_override: Option<Grid>,
    ) -> Result<Self, ScenarioError> {
        let cx = Ctx { path, src };
        let file: FileToml = toml::from_str(src).map_err(|e| {
            let span = e.span().unwrap_or(0..0);
            let key = key_at(src, &span);
            cx.err(span, &key, e.message().trim())
        })?;

        let mut spec = ModelSpec {
            loads: Vec::new(),
            ..ModelSpec::thesis_example()
        };
        if let Some(g) = &file.grid {
            let [nx, ny, nz] = *g.get_ref();
            spec.grid = Grid::new(nx, ny, nz).map_err(|e| cx.err(g.span(), "grid", e))?;
        }
        if let Some(grid) = grid_override {
            spec.grid = grid;
        }
        if let Some(m) = file.model {
            spec.connection = match m {
                ModelName::A => Connection::Axial,
                ModelName::B => Connection::AxialShear,
            };
        }
        if let Some(e) = &file.elasticity {
            cx.elasticity(e, &mut spec)?;
        }
        if let Some(b) = &file.boundary {
            cx.boundary(b, &mut spec)?;
        }
        if let Some(l) = &file.loads {
            cx.loads(l, &mut spec)?;
        }
        let solver = match file.solver {
            None => SolverSettings::default(),
            Some(s) => cx.solver(s)?,
        };
        let simulation = match &file.simulation {
            None => None,
            Some(sim) => Some(resolve_simulation(&cx, spec.grid, sim)?),
        };
        if let Some(sim) = &simulation {
            sim.apply_at_end(&mut spec);
        }
        let dynamics = match &file.dynamics {
            None => None,
            Some(d) => Some(dynamics::resolve_dynamics(&cx, spec.grid, d)?),
        };
        Ok(Scenario {
            path: path.to_path_buf(),
            model: spec,
            solver,
            out: file.output.and_then(|o| o.out),
            simulation,
            dynamics,
        })
    }
}

impl Ctx<'_> {
    /// `[elasticity]`: the homogeneous k, and a heterogeneous field if any part of one is given.
    fn elasticity(&self, e: &ElasticityToml, spec: &mut ModelSpec) -> Result<(), ScenarioError> {
        let mut single_k = None;
        if let Some(k) = &e.k {
            let el = match k.get_ref() {
                KToml::One(v) => {
                    single_k = Some(*v);
                    Elasticity::isotropic(*v)
                }
                KToml::Three([x, y, z]) => Elasticity::new(*x, *y, *z),
            };
            spec.elasticity = el.map_err(|err| self.err(k.span(), "elasticity.k", err))?;
        }
        if e.background.is_none() && e.inclusion.is_empty() && e.field.is_none() {
            return Ok(());
        }
        let background = match (&e.background, single_k) {
            (Some(b), _) => (*b.get_ref(), b.span()),
            (None, Some(k)) => (k, e.k.as_ref().map_or(0..0, |k| k.span())),
            (None, None) => {
                let span = e
                    .inclusion
                    .first()
                    .map(|i| i.span())
                    .or_else(|| e.k.as_ref().map(|k| k.span()))
                    .or_else(|| e.field.as_ref().map(|f| f.span()))
                    .unwrap_or(0..0);
                return Err(self.err(
                    span,
                    "elasticity.background",
                    "a heterogeneous field (inclusion or field) needs one background stiffness: set background = K, or k = K (a single number)",
                ));
            }
        };
        let parts = FieldParts {
            key: "elasticity",
            subkeys: true,
            quantity: field::STIFFNESS,
            background,
            inclusions: e
                .inclusion
                .iter()
                .map(|inc| InclusionAt {
                    center: inc.get_ref().center,
                    radius: inc.get_ref().radius,
                    value: inc.get_ref().k,
                    span: inc.span(),
                })
                .collect(),
            csv: e.field.as_ref().map(|f| (f.get_ref().as_str(), f.span())),
        };
        spec.field = Some(parts.resolve(self, spec.grid)?);
        Ok(())
    }

    /// `[boundary]`: fixed sets and nodes, prescribed displacements.
    fn boundary(&self, b: &BoundaryToml, spec: &mut ModelSpec) -> Result<(), ScenarioError> {
        let grid = spec.grid;
        if let Some(fix) = &b.fix {
            spec.fixed_sets = fix
                .iter()
                .map(|s| {
                    s.get_ref()
                        .parse::<FixedNodeSet>()
                        .map_err(|e| self.err(s.span(), "boundary.fix", e))
                })
                .collect::<Result<_, _>>()?;
        }
        for n in &b.fix_nodes {
            spec.fixed_nodes
                .push(self.node(grid, n, "boundary.fix_nodes")?);
        }
        for d in &b.displace {
            spec.prescribed.push(PrescribedDisplacement {
                node: self.node(grid, &d.node, "boundary.displace")?,
                u: self.finite(&d.u, "boundary.displace")?,
            });
        }
        Ok(())
    }

    /// `[loads]`: point loads and face pressures.
    fn loads(&self, l: &LoadsToml, spec: &mut ModelSpec) -> Result<(), ScenarioError> {
        for p in &l.point {
            spec.loads.push(PointLoad {
                node: self.node(spec.grid, &p.node, "loads.point")?,
                force: self.finite(&p.force, "loads.point")?,
            });
        }
        for p in &l.pressure {
            spec.pressures.push(FacePressure {
                face: p
                    .face
                    .get_ref()
                    .parse()
                    .map_err(|e| self.err(p.face.span(), "loads.pressure", e))?,
                force: self.finite(&p.force, "loads.pressure")?,
            });
        }
        Ok(())
    }

    /// `[solver]`, checked as the flags are.
    fn solver(&self, s: Spanned<SolverSettings>) -> Result<SolverSettings, ScenarioError> {
        let span = s.span();
        let s = s.into_inner();
        if let Some(t) = s.tol {
            if !(t.is_finite() && t > 0.0 && t < 1.0) {
                return Err(self.err(
                    span,
                    "solver.tol",
                    "the tolerance must be a number in (0, 1)",
                ));
            }
        }
        if s.max_solves == Some(0) {
            return Err(self.err(span, "solver.max_solves", "must be at least 1"));
        }
        if s.timeout == Some(0) {
            return Err(self.err(span, "solver.timeout", "must be at least 1 second"));
        }
        Ok(s)
    }
}

fn resolve_simulation(
    cx: &Ctx<'_>,
    grid: Grid,
    sim: &SimulationToml,
) -> Result<Simulation, ScenarioError> {
    let dt = *sim.dt.get_ref();
    if !(dt.is_finite() && dt > 0.0) {
        return Err(cx.err(
            sim.dt.span(),
            "simulation.dt",
            "must be finite and greater than 0",
        ));
    }
    if *sim.steps.get_ref() == 0 {
        return Err(cx.err(sim.steps.span(), "simulation.steps", "must be at least 1"));
    }
    let schedules =
        |list: &[ScheduleToml], key: &str| -> Result<Vec<NodeSchedule>, ScenarioError> {
            list.iter()
                .map(|s| {
                    let node = cx.node(grid, &s.node, key)?;
                    let frames = s.keyframes.get_ref();
                    if frames.is_empty() {
                        return Err(cx.err(
                            s.keyframes.span(),
                            key,
                            "keyframes: give at least one [t, x, y, z]",
                        ));
                    }
                    if frames.iter().flatten().any(|v| !v.is_finite()) {
                        return Err(cx.err(
                            s.keyframes.span(),
                            key,
                            "keyframes: every value must be finite",
                        ));
                    }
                    if frames.windows(2).any(|w| w[1][0] < w[0][0]) {
                        return Err(cx.err(
                            s.keyframes.span(),
                            key,
                            "keyframes must be sorted by time",
                        ));
                    }
                    Ok(NodeSchedule {
                        node,
                        keyframes: frames.clone(),
                        line: line_column(cx.src, s.node.span().start).0,
                    })
                })
                .collect()
        };
    Ok(Simulation {
        steps: *sim.steps.get_ref(),
        dt,
        displace: schedules(&sim.displace, "simulation.displace")?,
        load: schedules(&sim.load, "simulation.load")?,
        nonlinear: sim.nonlinear.clone(),
        dynamic: sim.dynamic.unwrap_or(false),
    })
}
