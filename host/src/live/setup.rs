//! What a live session sends once, and the f64 reference every frame is checked against.
//!
//! The tool nodes are the scenario's prescribed nodes. The matrix is the model's with them
//! eliminated, exactly as `deform solve` sends it; the static loads are the model's right-hand
//! sides with the tool held at zero; each tool node's row of the *unconstrained* K (its springs
//! to non-fixed nodes) lets the target move the tool's displacement into the right-hand side
//! and sum the reaction force.
//!
//! A force tool ([`LiveSetup::force`], protocol version 9) is the scenario's scheduled point
//! loads instead: its nodes stay free, the matrix is the model's own, the static loads leave
//! the tool's loads out (frames carry them), and the answer checked is the tool nodes' mean
//! displacement.

use deform_shared::live::{Coupling, ToolRow, MAX_TOOL_NODES, MAX_TOOL_ROW};
use deform_shared::qformat::quantize;

use crate::encode::{encode_with, EncodeOptions, EncodedMatrix};
use crate::model::assembly::assemble_laplacian;
use crate::model::springs::{MeanOfEndNodes, Uniform};
use crate::model::{Axis, Csr, Model, ModelError, ModelSpec, Node};
use crate::reference;
use crate::scenario::simulation::Simulation;

/// Why a live session cannot be set up.
#[derive(Debug, thiserror::Error)]
pub enum SetupError {
    #[error(
        "the scenario moves no tool: give [[simulation.displace]] keyframes (a displacement \
         tool) or [[simulation.load]] keyframes (a force tool)"
    )]
    NoTool,
    #[error("{0} tool nodes; a live session drives at most {MAX_TOOL_NODES}")]
    TooManyTools(usize),
    #[error("the tool tissue model: {0}")]
    Model(#[from] ModelError),
    #[error("assembling K: {0}")]
    Assembly(#[from] crate::model::assembly::AssemblyError),
    #[error("encoding K: {0}")]
    Encode(#[from] crate::encode::EncodeError),
    #[error(
        "tool node ({}, {}, {}) has {count} springs to free nodes; a tool row holds {MAX_TOOL_ROW}", .node.i, .node.j, .node.k
    )]
    RowTooLong { node: Node, count: usize },
    #[error("a tool row value does not fit the matrix's Q-format: {0}")]
    Quantize(#[from] deform_shared::qformat::QFormatError),
    #[error("f64 reference: {0}")]
    Reference(#[from] reference::SolveError),
    #[error("force tool node ({}, {}, {}) is fixed or prescribed: a load there moves nothing", .0.i, .0.j, .0.k)]
    FixedToolNode(Node),
    #[error("force tool node ({}, {}, {}) is outside the grid", .0.i, .0.j, .0.k)]
    ToolOutsideGrid(Node),
    #[error("force tool node ({}, {}, {}) is loaded by two schedules; give one", .0.i, .0.j, .0.k)]
    DuplicateToolNode(Node),
    #[error(
        "both [[simulation.displace]] and [[simulation.load]] keyframes: a live tool either moves \
         nodes (displacement tool) or loads them (force tool), not both; keep one kind"
    )]
    BothKinds,
}

/// What a live session's tool prescribes (see the module doc).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ToolKind {
    /// Prescribed displacements in, reaction force out.
    Displacement,
    /// Point loads in, the tool nodes' mean displacement out.
    Force,
}

impl ToolKind {
    /// The name the report and the CLI use.
    pub fn name(self) -> &'static str {
        match self {
            ToolKind::Displacement => "displacement",
            ToolKind::Force => "force",
        }
    }
}

/// One tool node's row of the unconstrained K in f64: (column, value), diagonal included.
pub type RowF64 = Vec<(usize, f64)>;

/// Everything a live session uploads once, and its f64 twin.
pub struct LiveSetup {
    pub kind: ToolKind,
    /// The model with the tool at rest (its prescribed displacements, or loads, zero).
    pub model: Model,
    /// Tool node indices, in the order frames give their displacements.
    pub tools: Vec<usize>,
    /// The rows as the target gets them (raw values in the matrix's Q-format; none for a
    /// force tool).
    pub rows: Vec<ToolRow>,
    /// The same rows in f64, diagonal included.
    pub rows_f64: Vec<RowF64>,
    pub matrix: EncodedMatrix,
    /// The static right-hand sides for the unit matrix (loads / k_d, zero at the tool).
    pub static_rhs: [Vec<f64>; 3],
    /// k_d: forces are k_d times the unit matrix's.
    pub scale: [f64; 3],
}

impl LiveSetup {
    /// Sets up a session for `spec`, whose prescribed nodes are the tool.
    pub fn new(spec: &ModelSpec, layout: &EncodeOptions) -> Result<Self, SetupError> {
        if spec.prescribed.is_empty() {
            return Err(SetupError::NoTool);
        }
        if spec.prescribed.len() > MAX_TOOL_NODES {
            return Err(SetupError::TooManyTools(spec.prescribed.len()));
        }
        let mut rest = spec.clone();
        for p in &mut rest.prescribed {
            p.u = [0.0; 3];
        }
        let model = Model::build(&rest)?;
        let grid = model.grid();
        let tools: Vec<usize> = spec
            .prescribed
            .iter()
            .filter_map(|p| grid.index(p.node))
            .collect();
        let free = if model.is_heterogeneous() {
            assemble_laplacian(
                grid,
                spec.connection,
                &MeanOfEndNodes(model.node_stiffness()),
            )?
        } else {
            assemble_laplacian(grid, spec.connection, &Uniform(1.0))?
        };
        let rows_f64: Vec<RowF64> = tools
            .iter()
            .map(|&t| {
                let (cols, vals) = free.row(t);
                cols.iter()
                    .zip(vals)
                    .filter(|(&c, _)| !model.fixed_mask()[c])
                    .map(|(&c, &v)| (c, v))
                    .collect()
            })
            .collect();
        let matrix = encode_with(model.unit_matrix(), layout)?.matrix;
        let rows = tools
            .iter()
            .zip(&rows_f64)
            .map(|(&t, row)| tool_row(t, row, matrix.frac_bits, &model))
            .collect::<Result<_, _>>()?;
        let static_rhs = Axis::ALL.map(|d| model.scaled_rhs(d));
        let scale = Axis::ALL.map(|d| model.direction_scale(d));
        Ok(LiveSetup {
            kind: ToolKind::Displacement,
            model,
            tools,
            rows,
            rows_f64,
            matrix,
            static_rhs,
            scale,
        })
    }

    /// The session a scenario's `[simulation]` describes (`model` is the scenario's static
    /// model): prescribed-displacement schedules make a displacement tool, point-load
    /// schedules a force tool; both at once are refused.
    pub fn for_simulation(
        model: &ModelSpec,
        simulation: &Simulation,
        layout: &EncodeOptions,
    ) -> Result<Self, SetupError> {
        let mut rest = simulation.spec_at(model, 0.0);
        match (simulation.displace.is_empty(), simulation.load.is_empty()) {
            (false, true) => Self::new(&rest, layout),
            (true, false) => {
                // The scenario appends the scheduled loads after the static ones: drop them,
                // the frames carry them.
                let statics = rest.loads.len().saturating_sub(simulation.load.len());
                rest.loads.truncate(statics);
                let nodes: Vec<Node> = simulation.load.iter().map(|s| s.node).collect();
                Self::force(&rest, &nodes, layout)
            }
            (false, false) => Err(SetupError::BothKinds),
            (true, true) => Err(SetupError::NoTool),
        }
    }

    /// The tool's inputs at time t: the prescribed displacements, or the loads.
    pub fn tool_at(&self, model: &ModelSpec, simulation: &Simulation, t: f64) -> Vec<[f64; 3]> {
        if self.kind == ToolKind::Force {
            return simulation.load.iter().map(|s| s.value_at(t)).collect();
        }
        let spec = simulation.spec_at(model, t);
        let grid = self.model.grid();
        self.tools
            .iter()
            .map(|&p| {
                let node = grid.node(p);
                spec.prescribed
                    .iter()
                    .find(|d| d.node == node)
                    .map_or([0.0; 3], |d| d.u)
            })
            .collect()
    }

    /// Sets up a force tool at `nodes` on `rest`, the model without the tool's loads.
    pub fn force(
        rest: &ModelSpec,
        nodes: &[Node],
        layout: &EncodeOptions,
    ) -> Result<Self, SetupError> {
        if nodes.is_empty() {
            return Err(SetupError::NoTool);
        }
        if nodes.len() > MAX_TOOL_NODES {
            return Err(SetupError::TooManyTools(nodes.len()));
        }
        let model = Model::build(rest)?;
        let grid = model.grid();
        let mut tools = Vec::new();
        for &node in nodes {
            let p = grid.index(node).ok_or(SetupError::ToolOutsideGrid(node))?;
            let constrained =
                model.fixed_mask()[p] || rest.prescribed.iter().any(|d| d.node == node);
            if constrained {
                return Err(SetupError::FixedToolNode(node));
            }
            if tools.contains(&p) {
                return Err(SetupError::DuplicateToolNode(node));
            }
            tools.push(p);
        }
        let matrix = encode_with(model.unit_matrix(), layout)?.matrix;
        Ok(LiveSetup {
            kind: ToolKind::Force,
            static_rhs: Axis::ALL.map(|d| model.scaled_rhs(d)),
            scale: Axis::ALL.map(|d| model.direction_scale(d)),
            model,
            tools,
            rows: Vec::new(),
            rows_f64: Vec::new(),
            matrix,
        })
    }

    /// The unit matrix the target holds (a displacement tool's nodes eliminated).
    pub fn unit_matrix(&self) -> &Csr {
        self.model.unit_matrix()
    }

    /// The right-hand side of direction d with the tool at `tool`: the tool's displacement
    /// moved over as [`Model::build`] does (b_i −= A_it·u_t, b_t = A_tt·u_t), or for a force
    /// tool its loads added (b_t += f_t/k_d).
    pub fn rhs(&self, d: usize, tool: &[[f64; 3]]) -> Vec<f64> {
        let mut b = self.static_rhs[d].clone();
        if self.kind == ToolKind::Force {
            for (&t, f) in self.tools.iter().zip(tool) {
                b[t] += f[d] / self.scale[d];
            }
            return b;
        }
        for ((&t, row), u) in self.tools.iter().zip(&self.rows_f64).zip(tool) {
            for &(c, v) in row {
                if c == t {
                    b[t] = v * u[d];
                } else if !self.tools.contains(&c) {
                    b[c] -= v * u[d];
                }
            }
        }
        b
    }

    /// Reaction force Σ_t (K·u)_t per direction, with the tool nodes at `tool`.
    pub fn reaction(&self, u: &[Vec<f64>; 3], tool: &[[f64; 3]]) -> [f64; 3] {
        [0, 1, 2].map(|d| {
            let mut sum = 0.0;
            for row in &self.rows_f64 {
                for &(c, v) in row {
                    let uc = match self.tools.iter().position(|&t| t == c) {
                        Some(j) => tool[j][d],
                        None => u[d][c],
                    };
                    sum += v * uc;
                }
            }
            self.scale[d] * sum
        })
    }

    /// A frame's answer from the solution `u` with the tool at `tool`: the reaction force, or
    /// for a force tool the tool nodes' mean displacement.
    pub fn answer(&self, u: &[Vec<f64>; 3], tool: &[[f64; 3]]) -> [f64; 3] {
        match self.kind {
            ToolKind::Displacement => self.reaction(u, tool),
            ToolKind::Force => [0, 1, 2].map(|d| {
                let sum: f64 = self.tools.iter().map(|&t| u[d][t]).sum();
                sum / self.tools.len().max(1) as f64
            }),
        }
    }

    /// The converged f64 solution of one frame (relative residual 1e-12) and its answer
    /// (reaction force, or mean tool displacement): what every target frame is checked
    /// against. `warm` starts the CG.
    pub fn converged(
        &self,
        tool: &[[f64; 3]],
        warm: Option<&[Vec<f64>; 3]>,
    ) -> Result<([Vec<f64>; 3], [f64; 3]), SetupError> {
        let k = self.unit_matrix();
        let n = k.n();
        let mut u: [Vec<f64>; 3] = Default::default();
        for (d, ud) in u.iter_mut().enumerate() {
            let b = self.rhs(d, tool);
            let x0 = warm.map(|w| w[d].as_slice());
            *ud = reference::solve(k, &b, x0, 1e-12, 20 * n.max(100))?.x;
        }
        let answer = self.answer(&u, tool);
        Ok((u, answer))
    }
}

/// The target's form of tool node t's row: off-diagonal entries to non-fixed nodes.
fn tool_row(t: usize, row: &RowF64, frac_bits: u8, model: &Model) -> Result<ToolRow, SetupError> {
    let off: Vec<_> = row.iter().filter(|(c, _)| *c != t).collect();
    if off.len() > MAX_TOOL_ROW {
        return Err(SetupError::RowTooLong {
            node: model.node(t),
            count: off.len(),
        });
    }
    let diagonal = row.iter().find(|(c, _)| *c == t).map_or(0.0, |(_, v)| *v);
    let mut out = heapless::Vec::new();
    for &&(column, v) in &off {
        let _ = out.push(Coupling {
            column: column as u32,
            value: quantize(v, frac_bits)?,
        });
    }
    Ok(ToolRow {
        node: t as u32,
        diagonal: quantize(diagonal, frac_bits)?,
        row: out,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::prescribed::PrescribedDisplacement;

    fn needle(u: [f64; 3]) -> ModelSpec {
        let mut spec = ModelSpec::thesis_example();
        spec.grid = crate::model::Grid::new(5, 5, 5).unwrap();
        spec.connection = crate::model::springs::Connection::AxialShear;
        spec.loads = vec![ModelSpec::default_load(spec.grid)];
        spec.prescribed = vec![PrescribedDisplacement {
            node: Node { i: 2, j: 2, k: 4 },
            u,
        }];
        spec
    }

    /// The right-hand side moved over by the live setup equals the model's own.
    #[test]
    fn the_rhs_equals_the_models_with_the_tool_prescribed() {
        let u = [0.2, -0.1, -0.7];
        let setup = LiveSetup::new(&needle(u), &EncodeOptions::default()).unwrap();
        let model = Model::build(&needle(u)).unwrap();
        for (d, axis) in Axis::ALL.into_iter().enumerate() {
            let want = model.scaled_rhs(axis);
            let got = setup.rhs(d, &[u]);
            let err = reference::max_abs_diff(&got, &want);
            assert!(err < 1e-12, "direction {d}: {err}");
        }
        // A node of the top face has 17 neighbours in model B.
        assert_eq!(setup.rows[0].row.len(), 17);
        // The reaction equals the model's K·u at the tool node, summed with k_d.
        let (x, force) = setup.converged(&[u], None).unwrap();
        let k = Model::build(&needle(u)).unwrap();
        for (d, axis) in Axis::ALL.into_iter().enumerate() {
            let full = assemble_laplacian(k.grid(), k.spec().connection, &Uniform(1.0)).unwrap();
            let mut y = vec![0.0; k.n()];
            full.mul_vec_into(&x[d], &mut y);
            let want = k.direction_scale(axis) * y[setup.tools[0]];
            assert!(
                (force[d] - want).abs() < 1e-9,
                "{d}: {} vs {want}",
                force[d]
            );
        }
    }

    /// A force tool's frame is the model with the tool's load added: same right-hand side,
    /// and the answer is the loaded node's displacement.
    #[test]
    fn a_force_tool_frame_is_the_model_with_its_load() {
        let f = [0.5, -0.25, -1.0];
        let probe = Node { i: 2, j: 2, k: 4 };
        let mut rest = needle([0.0; 3]);
        rest.prescribed.clear();
        rest.fixed_sets = vec![crate::model::FixedNodeSet::Face {
            axis: Axis::Z,
            side: crate::model::Side::Low,
        }];
        let setup = LiveSetup::force(&rest, &[probe], &EncodeOptions::default()).unwrap();
        let mut loaded = rest.clone();
        loaded.loads.push(crate::model::PointLoad {
            node: probe,
            force: f,
        });
        let model = Model::build(&loaded).unwrap();
        let (u, answer) = setup.converged(&[f], None).unwrap();
        let t = setup.tools[0];
        for (d, axis) in Axis::ALL.into_iter().enumerate() {
            let err = reference::max_abs_diff(&setup.rhs(d, &[f]), &model.scaled_rhs(axis));
            assert!(err < 1e-12, "direction {d}: {err}");
            assert_eq!(answer[d], u[d][t]);
        }
        // The base is fixed: a tool there is refused.
        let base = Node { i: 2, j: 2, k: 0 };
        assert!(matches!(
            LiveSetup::force(&rest, &[base], &EncodeOptions::default()),
            Err(SetupError::FixedToolNode(_))
        ));
    }

    #[test]
    fn a_scenario_without_a_tool_is_refused() {
        let spec = ModelSpec::thesis_example();
        assert!(matches!(
            LiveSetup::new(&spec, &EncodeOptions::default()),
            Err(SetupError::NoTool)
        ));
    }
}
