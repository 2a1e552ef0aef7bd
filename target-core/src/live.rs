//! The target's half of the live loop (`deform live`, protocol versions 8–9; the messages and
//! the scheme are in [`deform_shared::live`]): the tool set of either [`ToolKind`], the local
//! model (Schur sums, or compliance means for a force tool), and the integer arithmetic that
//! turns a frame's few tool inputs (displacements, or loads) into right-hand sides, answers
//! (reaction forces, or the tool's mean displacement) and a quantised field. The session ([`crate::session`]) owns the vectors and runs the solves;
//! this module only computes on what it is lent.
//!
//! Everything per frame is integer work on the few rows the tool touches, never a pass of soft
//! float over n: a frame's right-hand side differs from the static one only in the tool nodes'
//! free neighbours and the tool rows themselves.

use deform_shared::live::{
    Coupling, LiveError, LiveParams, ToolRow, FIELD_COMPONENTS, MAX_TOOL_NODES, MAX_TOOL_ROW,
};
use deform_shared::qformat::{block_exponent, ldexp, to_mantissa};
use deform_shared::word::{VALUE_MAX, VALUE_MIN};
use heapless::Vec;

use crate::predict::{bits, scale, TOP_BITS};
use crate::superpose::Column;

/// Most distinct free rows the tool nodes couple to.
pub const MAX_ROWS: usize = MAX_TOOL_NODES * MAX_TOOL_ROW;

/// Marks a coupling to another tool node in [`Started::slots`].
const TOOL_COLUMN: u16 = u16::MAX;

/// What a tool prescribes, and so what a frame carries and what it answers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum ToolKind {
    /// The tool nodes are eliminated; frames carry their displacements and get the force.
    #[default]
    Displacement,
    /// The tool nodes are free (version 9); frames carry point loads and get the motion.
    Force,
}

/// The live state of a session: the tool set as it arrives, then what `LiveStart` computed.
/// A force tool's nodes are kept as [`ToolRow`]s without couplings, so both kinds share the
/// set's bookkeeping.
#[derive(Default)]
pub struct Live {
    tools: Vec<ToolRow, MAX_TOOL_NODES>,
    kind: ToolKind,
    started: Option<Started>,
}

/// A started live session.
pub struct Started {
    pub params: LiveParams,
    pub kind: ToolKind,
    /// The free rows the tools couple to (node indices), each once.
    rows: Vec<u32, MAX_ROWS>,
    /// For each tool and each of its couplings, the index into `rows`, or [`TOOL_COLUMN`].
    slots: [[u16; MAX_TOOL_ROW]; MAX_TOOL_NODES],
    /// The local model's columns, of the resident matrix (before k_d): for a displacement
    /// tool the column sums s_j of the Schur complement K_tt − K_tf·K_ff⁻¹·K_ft, for a force
    /// tool the column means c̄_j of the compliance block (K⁻¹)_tt.
    pub model: [f64; MAX_TOOL_NODES],
    /// Per direction, the static loads at the coupled rows, taken from the first frame's b.
    snapshot: [Option<Snapshot>; 3],
    /// The last full frame: its answer (forces, or the tool's mean displacement) and its input
    /// (tool displacements, or loads), the local model's anchor.
    anchor: Option<([f64; 3], [[f32; 3]; MAX_TOOL_NODES])>,
    /// The field's exponent for the last frame, once a chunk asked for it.
    pub field_exponent: Option<i8>,
    /// The model's solved columns held in the session's response storage, in tool order
    /// ([`crate::superpose`]); `None` if they did not all fit.
    pub columns: Option<Vec<Column, MAX_TOOL_NODES>>,
    /// The columns' own residuals ρ_j = c_j − K·G_j, held beside them as `i16` mantissas,
    /// each with the bound of its stored error (real units); `None` where not held.
    pub residual_columns: Option<Vec<(Column, f64), MAX_TOOL_NODES>>,
    /// The tool input the solutions in x belong to, while they are a live frame's: the
    /// superposition predictor's anchor. Any other solve clears it.
    pub base: Option<[[f32; 3]; MAX_TOOL_NODES]>,
    /// Per direction, what the residual estimate of the next frame starts from (valid while
    /// `base` is).
    pub estimates: [Option<Estimate>; 3],
}

/// A direction's residual in r for the solution in x at a live frame's end: the start of the
/// next frame's estimate ([`crate::superpose`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Estimate {
    pub r_exponent: i32,
    /// Bounds on max |r| and max |x| (mantissa units).
    pub r_bound: u64,
    pub x_bound: u64,
    /// A bound on ‖r₀ − r‖₂ (real units), r₀ the exact residual of the mantissas; infinite
    /// where r is the recursive residual.
    pub error: f64,
    /// Frames since r was formed by an exact pass.
    pub frames: u32,
    /// The frame's right-hand side exponent and tool inputs' exponent (their rounding enters
    /// the next frame's bound).
    pub b_exponent: i32,
    pub input_exponent: i32,
}

/// The static right-hand side of one direction, as far as frames need it.
#[derive(Clone)]
struct Snapshot {
    exponent: i32,
    /// Static mantissas at `rows`.
    at_rows: Vec<i32, MAX_ROWS>,
    /// Top bit (magnitude bits + exponent) of the static loads elsewhere, if there are any:
    /// then b keeps them in place and its exponent can only grow.
    elsewhere_top: Option<i32>,
}

impl Live {
    /// Forgets the tool set (a new matrix, a `Hello`).
    pub fn clear(&mut self) {
        *self = Live::default();
    }

    pub fn started(&self) -> Option<&Started> {
        self.started.as_ref()
    }

    pub fn started_mut(&mut self) -> Result<&mut Started, LiveError> {
        self.started.as_mut().ok_or(LiveError::NotStarted)
    }

    pub fn tools(&self) -> &[ToolRow] {
        &self.tools
    }

    /// The tool rows and the started session, borrowed together.
    pub fn parts(&mut self) -> Result<(&[ToolRow], &mut Started), LiveError> {
        let Live { tools, started, .. } = self;
        Ok((tools, started.as_mut().ok_or(LiveError::NotStarted)?))
    }

    /// A right-hand side of direction `d` was uploaded: it is the new static load, and the
    /// residual in r no longer belongs to it.
    pub fn rhs_replaced(&mut self, d: usize) {
        if let Some(started) = self.started.as_mut() {
            if let Some(s) = started.snapshot.get_mut(d) {
                *s = None;
            }
            if let Some(e) = started.estimates.get_mut(d) {
                *e = None;
            }
        }
    }

    /// Adds a tool node of an n-node matrix. A tool row after `LiveStart` begins a new set.
    pub fn add_tool(&mut self, row: ToolRow, n: u32) -> Result<(), LiveError> {
        if self.started.take().is_some() {
            self.tools.clear();
        }
        if self.kind == ToolKind::Force && !self.tools.is_empty() {
            return Err(LiveError::MixedKinds);
        }
        self.kind = ToolKind::Displacement;
        if row.node >= n {
            return Err(LiveError::NodeOutOfRange { node: row.node });
        }
        if let Some(c) = row.row.iter().find(|c| c.column >= n) {
            return Err(LiveError::ColumnOutOfRange { column: c.column });
        }
        let fits = |v: i32| (VALUE_MIN..=VALUE_MAX).contains(&v);
        if !fits(row.diagonal) || !row.row.iter().all(|c| fits(c.value)) {
            return Err(LiveError::ValueOutOfRange);
        }
        if self.tools.iter().any(|t| t.node == row.node) {
            return Err(LiveError::DuplicateNode { node: row.node });
        }
        self.tools.push(row).map_err(|_| LiveError::TooManyNodes {
            max: MAX_TOOL_NODES as u8,
        })
    }

    /// Sets a force tool at `nodes` of an n-node matrix, replacing a force tool or a started
    /// session's tools. Displacement rows given since the last start are refused: the kinds
    /// do not mix. Whether a node is fixed shows only in its model column (see
    /// [`Started::set_model_column`]).
    pub fn set_force_tool(&mut self, nodes: &[u32], n: u32) -> Result<(), LiveError> {
        if self.started.take().is_some() {
            self.tools.clear();
        }
        if self.kind == ToolKind::Displacement && !self.tools.is_empty() {
            return Err(LiveError::MixedKinds);
        }
        self.tools.clear();
        self.kind = ToolKind::Force;
        for &node in nodes {
            if node >= n {
                self.tools.clear();
                return Err(LiveError::NodeOutOfRange { node });
            }
            if self.tools.iter().any(|t| t.node == node) {
                self.tools.clear();
                return Err(LiveError::DuplicateNode { node });
            }
            // At most MAX_TOOL_NODES nodes arrive: always room.
            let _ = self.tools.push(ToolRow {
                node,
                diagonal: 0,
                row: Vec::new(),
            });
        }
        Ok(())
    }

    /// Starts the session with the tools given so far; the model's columns are filled in by
    /// [`Started::set_model_column`] afterwards.
    pub fn start(&mut self, params: LiveParams) -> Result<&mut Started, LiveError> {
        if self.tools.is_empty() {
            return Err(LiveError::NoTool);
        }
        let finite = params.tolerance.is_finite() && params.scale.iter().all(|s| s.is_finite());
        if !finite {
            return Err(LiveError::NotFinite);
        }
        let mut rows: Vec<u32, MAX_ROWS> = Vec::new();
        let mut slots = [[TOOL_COLUMN; MAX_TOOL_ROW]; MAX_TOOL_NODES];
        for (t, tool) in self.tools.iter().enumerate() {
            for (k, c) in tool.row.iter().enumerate() {
                if self.tools.iter().any(|o| o.node == c.column) {
                    continue;
                }
                let slot = match rows.iter().position(|&r| r == c.column) {
                    Some(i) => i,
                    None => {
                        // At most MAX_TOOL_NODES · MAX_TOOL_ROW distinct rows: always room.
                        let _ = rows.push(c.column);
                        rows.len() - 1
                    }
                };
                slots[t][k] = slot as u16;
            }
        }
        if self.kind == ToolKind::Force {
            // A force frame rewrites the tool nodes' own loads, nothing else.
            for t in &self.tools {
                let _ = rows.push(t.node);
            }
        }
        Ok(self.started.insert(Started {
            params,
            kind: self.kind,
            rows,
            slots,
            model: [0.0; MAX_TOOL_NODES],
            snapshot: [None, None, None],
            anchor: None,
            field_exponent: None,
            columns: None,
            residual_columns: None,
            base: None,
            estimates: [None; 3],
        }))
    }
}

/// The tool's inputs of direction `d` (displacements, or loads), times `factor`, as mantissas
/// with one exponent.
pub fn tool_mantissas(
    tool: &[[f32; 3]],
    d: usize,
    factor: f64,
) -> Result<(Vec<i32, MAX_TOOL_NODES>, i32), LiveError> {
    let max = tool
        .iter()
        .fold(0f64, |m, u| m.max((f64::from(u[d]) * factor).abs()));
    if !max.is_finite() {
        return Err(LiveError::NotFinite);
    }
    let e = block_exponent(max);
    let mut out = Vec::new();
    for u in tool {
        let m = to_mantissa(f64::from(u[d]) * factor, e).ok_or(LiveError::NotFinite)?;
        let _ = out.push(m);
    }
    Ok((out, e))
}

/// Tool row `t`'s couplings, each with its slot in [`Started::rows`] (or [`TOOL_COLUMN`]).
fn couplings<'a>(
    tools: &'a [ToolRow],
    started: &'a Started,
    t: usize,
) -> impl Iterator<Item = (&'a Coupling, u16)> + 'a {
    let slots = started
        .slots
        .get(t)
        .copied()
        .unwrap_or([TOOL_COLUMN; MAX_TOOL_ROW]);
    tools
        .get(t)
        .map(|tool| tool.row.as_slice())
        .unwrap_or(&[])
        .iter()
        .zip(slots)
}

/// Index of the tool at node `column`, if it is one.
fn tool_index(tools: &[ToolRow], column: u32) -> Option<usize> {
    tools.iter().position(|t| t.node == column)
}

impl Started {
    /// Takes the static loads of direction `d` from `b` (exponent `e`) if not yet done, and
    /// zeroes the rows frames rewrite.
    pub fn take_snapshot(&mut self, d: usize, tools: &[ToolRow], b: &mut [i32], e: i32) {
        let Some(slot) = self.snapshot.get_mut(d) else {
            return;
        };
        if slot.is_some() {
            return;
        }
        let mut at_rows = Vec::new();
        for &r in &self.rows {
            let v = b.get_mut(r as usize).map_or(0, core::mem::take);
            let _ = at_rows.push(v);
        }
        for t in tools {
            if let Some(v) = b.get_mut(t.node as usize) {
                *v = 0;
            }
        }
        let max = b.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0);
        *slot = Some(Snapshot {
            exponent: e,
            at_rows,
            elsewhere_top: (max != 0).then(|| bits(u64::from(max)) + e),
        });
    }

    /// Moves the tool displacements `u` (mantissas, exponent `e_u`) of direction `d` into b,
    /// whose current exponent is `e_b`: b_i = static_i − Σ_t K_it·u_t on the coupled rows,
    /// b_t = K_tt·u_t on the tool rows, the rest left as it is. `f` is the matrix's Q-format.
    /// Returns b's new exponent.
    #[allow(clippy::too_many_arguments)]
    pub fn patch_rhs(
        &self,
        d: usize,
        tools: &[ToolRow],
        b: &mut [i32],
        e_b: i32,
        u: &[i32],
        e_u: i32,
        f: i32,
    ) -> i32 {
        let Some(Some(snap)) = self.snapshot.get(d) else {
            return e_b;
        };
        // Σ_t K_it·u_t per coupled row, exactly: |raw| < 2^20, |u| < 2^30, ≤ 256 terms. Only
        // the rows in use are zeroed (the array is large, the rows few).
        let mut sums: Vec<i64, MAX_ROWS> = Vec::new();
        let _ = sums.resize(self.rows.len(), 0);
        let mut diag = [0i64; MAX_TOOL_NODES];
        for (t, tool) in tools.iter().enumerate() {
            let ut = i64::from(u.get(t).copied().unwrap_or(0));
            diag[t] = i64::from(tool.diagonal) * ut;
            for (c, slot) in couplings(tools, self, t) {
                if let Some(s) = sums.get_mut(usize::from(slot)) {
                    *s += i64::from(c.value) * ut;
                }
            }
        }
        let e_tool = e_u - f;
        let nodes = tools.iter().map(|t| t.node);
        self.write_rows(snap, b, e_b, &sums, nodes.zip(diag), e_tool)
    }

    /// Adds the point loads `load` (mantissas of f/k_d, exponent `e_l`) of direction `d` to
    /// the static loads at a force tool's nodes in b (exponent `e_b`). Returns b's new exponent.
    pub fn patch_load(&self, d: usize, b: &mut [i32], e_b: i32, load: &[i32], e_l: i32) -> i32 {
        let Some(Some(snap)) = self.snapshot.get(d) else {
            return e_b;
        };
        // `rows` are the tool nodes in the tool's order: b_t = static_t − (−f_t).
        let mut minus = [0i64; MAX_TOOL_NODES];
        for (m, &l) in minus.iter_mut().zip(load) {
            *m = -i64::from(l);
        }
        let n = self.rows.len().min(MAX_TOOL_NODES);
        self.write_rows(snap, b, e_b, &minus[..n], core::iter::empty(), e_l)
    }

    /// Writes a frame's rows into b (exponent `e_b`): b_r = static_r − sums_r on `rows`,
    /// b_node = own on each (node, own) of `own_rows`, the terms at exponent `e_tool`. Picks
    /// the exponent that holds them all and returns it.
    fn write_rows(
        &self,
        snap: &Snapshot,
        b: &mut [i32],
        e_b: i32,
        sums: &[i64],
        own_rows: impl Iterator<Item = (u32, i64)> + Clone,
        e_tool: i32,
    ) -> i32 {
        let own_max = own_rows.clone().map(|(_, v)| v.unsigned_abs()).max();
        let tool_max = sums.iter().map(|v| v.unsigned_abs()).max().max(own_max);
        let static_max = snap.at_rows.iter().map(|v| v.unsigned_abs()).max();
        let tops = [
            tool_max.filter(|&m| m != 0).map(|m| bits(m) + e_tool),
            static_max
                .filter(|&m| m != 0)
                .map(|m| bits(u64::from(m)) + snap.exponent),
            snap.elsewhere_top,
        ];
        let Some(top) = tops.into_iter().flatten().max() else {
            // Nothing anywhere: b is zero.
            b.fill(0);
            return 0;
        };
        // Two terms below 2^top each: the sum stays below 2^(top + 1) = 2^(e + 29).
        let mut e = top + 1 - TOP_BITS;
        if snap.elsewhere_top.is_some() {
            // The static loads elsewhere stay in b: its exponent only grows.
            if e > e_b {
                for v in b.iter_mut() {
                    *v = scale(i64::from(*v), e - e_b) as i32;
                }
            } else {
                e = e_b;
            }
        }
        for (i, &r) in self.rows.iter().enumerate() {
            let s = snap.at_rows.get(i).copied().unwrap_or(0);
            let t = sums.get(i).copied().unwrap_or(0);
            let v = scale(i64::from(s), e - snap.exponent) - scale(t, e - e_tool);
            if let Some(slot) = b.get_mut(r as usize) {
                *slot = v as i32;
            }
        }
        for (node, v) in own_rows {
            if let Some(slot) = b.get_mut(node as usize) {
                *slot = scale(v, e - e_tool) as i32;
            }
        }
        e
    }

    /// Direction `d`'s tool inputs of a frame (`input`: displacements, or loads scaled by
    /// 1/k_d, by the tool's kind) as mantissas with one exponent: converted once per frame, for
    /// the right-hand side ([`Started::patch`]) and the answer ([`Started::answer`]).
    pub fn tool_input(
        &self,
        d: usize,
        input: &[[f32; 3]],
    ) -> Result<(Vec<i32, MAX_TOOL_NODES>, i32), LiveError> {
        let factor = match self.kind {
            ToolKind::Displacement => 1.0,
            ToolKind::Force => 1.0 / f64::from(self.params.scale.get(d).copied().unwrap_or(1.0)),
        };
        tool_mantissas(input, d, factor)
    }

    /// Builds direction `d`'s right-hand side of a frame whose tool inputs are `(m, e_m)`
    /// ([`Started::tool_input`]). Returns b's new exponent.
    #[allow(clippy::too_many_arguments)]
    pub fn patch(
        &self,
        d: usize,
        tools: &[ToolRow],
        b: &mut [i32],
        e_b: i32,
        (m, e_m): (&[i32], i32),
        f: i32,
    ) -> i32 {
        match self.kind {
            ToolKind::Displacement => self.patch_rhs(d, tools, b, e_b, m, e_m, f),
            ToolKind::Force => self.patch_load(d, b, e_b, m, e_m),
        }
    }

    /// The rows a frame's right-hand side rewrites (coupled rows and tool rows).
    pub fn patched_rows(&self, tools: usize) -> usize {
        self.rows.len()
            + match self.kind {
                ToolKind::Displacement => tools,
                ToolKind::Force => 0,
            }
    }

    /// A frame's answer in direction `d` from the solution `x` (exponent `e_x`) and the tool
    /// inputs `(m, e_m)` ([`Started::tool_input`]): the reaction force (displacement tool) or
    /// the tool nodes' mean displacement (force tool).
    pub fn answer(
        &self,
        d: usize,
        tools: &[ToolRow],
        x: &[i32],
        e_x: i32,
        (m, e_m): (&[i32], i32),
        f: i32,
    ) -> Result<f64, LiveError> {
        Ok(match self.kind {
            ToolKind::Displacement => {
                let k = f64::from(self.params.scale.get(d).copied().unwrap_or(1.0));
                k * self.reaction(tools, x, e_x, m, e_m, f)
            }
            ToolKind::Force => {
                let sum: i64 = tools
                    .iter()
                    .map(|t| i64::from(x.get(t.node as usize).copied().unwrap_or(0)))
                    .sum();
                ldexp(sum as f64, e_x) / tools.len().max(1) as f64
            }
        })
    }

    /// Reaction force of direction `d` before the factor k_d: Σ_t (K·u)_t with the free
    /// displacements from `x` (exponent `e_x`) and the tool ones from `u` (exponent `e_u`).
    pub fn reaction(
        &self,
        tools: &[ToolRow],
        x: &[i32],
        e_x: i32,
        u: &[i32],
        e_u: i32,
        f: i32,
    ) -> f64 {
        let (mut free, mut tool) = (0i64, 0i64);
        for (t, row) in tools.iter().enumerate() {
            tool += i64::from(row.diagonal) * i64::from(u.get(t).copied().unwrap_or(0));
            for (c, slot) in couplings(tools, self, t) {
                let v = i64::from(c.value);
                if slot == TOOL_COLUMN {
                    let j = tool_index(tools, c.column).unwrap_or(0);
                    tool += v * i64::from(u.get(j).copied().unwrap_or(0));
                } else {
                    free += v * i64::from(x.get(c.column as usize).copied().unwrap_or(0));
                }
            }
        }
        ldexp(free as f64, e_x - f) + ldexp(tool as f64, e_u - f)
    }

    /// The right-hand side whose solution z_j gives the model's column j: K_f,t_j for a
    /// displacement tool (exponent −f), the unit load at tool node j for a force tool.
    /// Returns its exponent.
    pub fn model_rhs(&self, tools: &[ToolRow], j: usize, b: &mut [i32], f: i32) -> i32 {
        match self.kind {
            ToolKind::Displacement => {
                self.schur_rhs(tools, j, b);
                -f
            }
            ToolKind::Force => {
                b.fill(0);
                let node = tools.get(j).map_or(usize::MAX, |t| t.node as usize);
                if let Some(v) = b.get_mut(node) {
                    *v = 1 << TOP_BITS;
                }
                -TOP_BITS
            }
        }
    }

    /// Column j of the model from its solution z_j (exponent `e_z`). A force tool node whose
    /// unit load moved no other node couples to nothing: it is fixed (or prescribed), and a
    /// load there would vanish into the support.
    pub fn set_model_column(
        &mut self,
        tools: &[ToolRow],
        j: usize,
        z: &[i32],
        e_z: i32,
        f: i32,
    ) -> Result<(), LiveError> {
        if self.kind == ToolKind::Displacement {
            self.set_schur(tools, j, z, e_z, f);
            return Ok(());
        }
        let node = tools.get(j).map_or(u32::MAX, |t| t.node);
        let moved_others = z
            .iter()
            .enumerate()
            .any(|(i, &v)| v != 0 && i != node as usize);
        if !moved_others {
            return Err(LiveError::FixedToolNode { node });
        }
        let sum: i64 = tools
            .iter()
            .map(|t| i64::from(z.get(t.node as usize).copied().unwrap_or(0)))
            .sum();
        if let Some(c) = self.model.get_mut(j) {
            *c = ldexp(sum as f64, e_z) / tools.len().max(1) as f64;
        }
        Ok(())
    }

    /// b = K_f,t_j (column j's couplings to the free nodes), exponent −f: the right-hand side
    /// whose solution z_j gives the Schur column j.
    fn schur_rhs(&self, tools: &[ToolRow], j: usize, b: &mut [i32]) {
        b.fill(0);
        for (c, slot) in couplings(tools, self, j) {
            if slot != TOOL_COLUMN {
                if let Some(v) = b.get_mut(c.column as usize) {
                    *v = c.value;
                }
            }
        }
    }

    /// s_j = Σ_i [K_t_i,t_j − K_t_i,f·z_j] from the solution z_j (exponent `e_z`).
    fn set_schur(&mut self, tools: &[ToolRow], j: usize, z: &[i32], e_z: i32, f: i32) {
        let Some(node_j) = tools.get(j).map(|t| t.node) else {
            return;
        };
        let mut tt = i64::from(tools[j].diagonal);
        let mut tf = 0i64;
        for t in 0..tools.len() {
            for (c, slot) in couplings(tools, self, t) {
                let v = i64::from(c.value);
                if slot == TOOL_COLUMN {
                    if c.column == node_j {
                        tt += v;
                    }
                } else {
                    tf += v * i64::from(z.get(c.column as usize).copied().unwrap_or(0));
                }
            }
        }
        if let Some(s) = self.model.get_mut(j) {
            *s = ldexp(tt as f64, -f) - ldexp(tf as f64, e_z - f);
        }
    }

    /// The superposition predictor's terms of direction `d` for a frame at tool inputs `now`
    /// after one at `then` (see [`crate::superpose`]): per column the coefficient a_j, and
    /// the tool nodes' own displacement changes. A displacement tool's free nodes move by
    /// −z_j·Δu_j (b_f = static − Σ_j K_f,t_j·u_j) and its nodes by Δu_j; a force tool's by
    /// K⁻¹e_j·Δf_j/k_d.
    pub fn superpose_terms(
        &self,
        d: usize,
        tools: &[ToolRow],
        now: &[[f32; 3]],
        then: &[[f32; 3]],
    ) -> ([f64; MAX_TOOL_NODES], Vec<(u32, f64), MAX_TOOL_NODES>) {
        let mut coeffs = [0f64; MAX_TOOL_NODES];
        let mut own = Vec::new();
        let k = f64::from(self.params.scale.get(d).copied().unwrap_or(1.0));
        for (j, ((c, a), b)) in coeffs.iter_mut().zip(now).zip(then).enumerate() {
            let du = f64::from(a[d]) - f64::from(b[d]);
            match self.kind {
                ToolKind::Displacement => {
                    *c = -du;
                    if let Some(t) = tools.get(j) {
                        let _ = own.push((t.node, du));
                    }
                }
                ToolKind::Force => *c = du / k,
            }
        }
        (coeffs, own)
    }

    /// Re-anchors the local model at a full frame.
    pub fn anchor(&mut self, force: [f64; 3], tool: &[[f32; 3]]) {
        let mut u = [[0f32; 3]; MAX_TOOL_NODES];
        for (a, b) in u.iter_mut().zip(tool) {
            *a = *b;
        }
        self.anchor = Some((force, u));
        self.field_exponent = None;
    }

    /// The local model's answer at tool inputs `tool`: the force F_frame + k_d·Σ_j s_j·Δu_j
    /// of a displacement tool, the mean displacement ū_frame + Σ_j c̄_j·Δf_j/k_d of a force tool.
    pub fn model_answer(&self, tool: &[[f32; 3]]) -> Result<[f64; 3], LiveError> {
        let (answer, at) = self.anchor.as_ref().ok_or(LiveError::NoFrame)?;
        let mut out = *answer;
        for (d, o) in out.iter_mut().enumerate() {
            let mut sum = 0f64;
            for (j, (now, then)) in tool.iter().zip(at).enumerate() {
                let du = f64::from(now[d]) - f64::from(then[d]);
                sum += self.model.get(j).copied().unwrap_or(0.0) * du;
            }
            let k = f64::from(self.params.scale[d]);
            *o += match self.kind {
                ToolKind::Displacement => k * sum,
                ToolKind::Force => sum / k,
            };
        }
        if out.iter().all(|v| v.is_finite()) {
            Ok(out)
        } else {
            Err(LiveError::NotFinite)
        }
    }
}

/// The field's exponent: the smallest that puts every component of the three solutions
/// (mantissas and exponents) into an `i16`.
pub fn field_exponent(solutions: &[(&[i32], i32)]) -> i8 {
    let top = solutions
        .iter()
        .filter_map(|(x, e)| {
            let max = x.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0);
            (max != 0).then(|| bits(u64::from(max)) + e)
        })
        .max();
    // |q| < 2^15 before rounding; rounding up to 2^15 is clamped.
    top.map_or(0, |t| {
        (t - 15).clamp(i32::from(i8::MIN), i32::from(i8::MAX)) as i8
    })
}

/// Quantises the three solutions at `nodes` to `i16` q at exponent `e`, node by node, as
/// many as one chunk holds (the wire's difference coding is [`deform_shared::field`]'s).
pub fn pack_field(
    solutions: &[(&[i32], i32)],
    nodes: impl Iterator<Item = u32>,
    e: i8,
) -> Vec<i16, FIELD_COMPONENTS> {
    let mut out = Vec::new();
    for node in nodes.take(FIELD_COMPONENTS / 3) {
        for (x, ex) in solutions {
            let m = x.get(node as usize).copied().unwrap_or(0);
            let _ = out.push(quantise(m, i32::from(e) - ex));
        }
    }
    out
}

/// m·2^−s rounded half up and clamped to ±32767, in 32 bits where it can be (rv32 has no
/// 64-bit shift): ((m >> (s−1)) + 1) >> 1 equals (m + 2^(s−1)) >> s without the overflow, and
/// from s = 32 on every i32 rounds to 0 (the small directions of a field, whose own exponents
/// are far below the frame's, are all in that case).
fn quantise(m: i32, s: i32) -> i16 {
    let q = match s {
        1..=31 => (m >> (s - 1)).saturating_add(1) >> 1,
        32.. => 0,
        _ => scale(i64::from(m), s).clamp(-32767, 32767) as i32,
    };
    q.clamp(-32767, 32767) as i16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_field_quantises_to_i16_with_one_exponent() {
        let (x, y, z) = ([1 << 29, -3, 0], [5, 7, -(1 << 20)], [0, 0, 0]);
        let solutions = [(&x[..], -40), (&y[..], -20), (&z[..], 0)];
        let e = field_exponent(&solutions);
        // max |u| = 2^−11 (x[0]) and 2^−20·2^20 = 1 (y[2]): the top is 1.
        assert_eq!(e, -14);
        let packed = pack_field(&solutions, [0, 2].into_iter(), e);
        assert_eq!(packed, [8, 0, 0, 0, -16384, 0], "nodes 0 and 2");
        assert_eq!(field_exponent(&[(&[0][..], 5)]), 0);
    }

    #[test]
    fn the_32_bit_quantiser_rounds_as_the_64_bit_one() {
        let slow = |m: i32, s: i32| scale(i64::from(m), s).clamp(-32767, 32767) as i16;
        let mut m = 0x1234_5678i32;
        for s in -3..=40 {
            for edge in [
                0,
                1,
                -1,
                2,
                -2,
                3,
                i32::MAX,
                i32::MIN,
                1 << 29,
                -(1 << 29),
                32767,
                -32768,
            ] {
                assert_eq!(quantise(edge, s), slow(edge, s), "{edge} >> {s}");
            }
            for _ in 0..2000 {
                m = m.wrapping_mul(1_103_515_245).wrapping_add(12_345);
                assert_eq!(quantise(m, s), slow(m, s), "{m} >> {s}");
                assert_eq!(quantise(m >> 3, s), slow(m >> 3, s), "{m} >> {s}");
            }
        }
    }
}
