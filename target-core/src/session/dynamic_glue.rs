//! The session's dynamic-frame requests (protocol version 12, [`deform_shared::dynamics`]): the
//! stiffness copy's upload, the tool set, the start and the steps. The arithmetic is in
//! [`crate::dynamics`]; this is where it meets the session's vectors, the MVU and the solves.
//!
//! While a dynamic session runs, each direction's x holds u (so `ReadSolution` and `ReadField`
//! read displacements, as for quasi-static frames, and the solution's exponent is u's), x0
//! holds v, b the step's right-hand side and r its residual.

// The passes share the vectors through `SharedSlice`s, each hart writing its own share.
#![allow(unsafe_code)]

use deform_shared::dynamics::{DynamicError, DynamicParams, DynamicTool};
use deform_shared::live::{FrameReport, LiveError, ToolRow, MAX_TOOL_NODES, MAX_TOOL_ROW};
use deform_shared::protocol::PhaseCounters;
use deform_shared::qformat::ldexp;

use super::*;
use crate::cg::{GivenResidual, Outcome};
use crate::dynamics::{
    advance_share, predict_share, residual_share, rhs_share, row_sum, start_local, Difference,
    History, LiveDynamicError, ResidualPlan, RhsPlan, RhsSums, MAX_UNCHECKED,
};
use crate::exec::{share, slowest, SharedSlice};
use crate::kernel::sum_rows;
use crate::svu::{bound_of, bound_of_u64, magnitude_bits, Block, Lin, Narrow, Scalar};
use crate::upper::Upper;

/// Runs `$body` with `$r` bound, as a constant, to Kp's layout `$words` (i64 words a row, 1 or
/// [`MAX_DIRECTIONS`]: [`cg::sum_words_for`]), as the step's K·u₀ laid Kp out.
macro_rules! with_sum_words {
    ($words:expr, |$r:ident| $body:expr) => {
        if $words == 1 {
            const $r: usize = 1;
            $body
        } else {
            const $r: usize = MAX_DIRECTIONS;
            $body
        }
    };
}

fn dynamic(e: DynamicError) -> ErrorCode {
    ErrorCode::Dynamic(e)
}

impl From<LiveDynamicError> for ErrorCode {
    fn from(e: LiveDynamicError) -> Self {
        match e {
            LiveDynamicError::Live(e) => ErrorCode::Live(e),
            LiveDynamicError::Dynamic(e) => ErrorCode::Dynamic(e),
        }
    }
}

/// Hart 0's counts over the parallel parts of a step and their critical path (see
/// `FrameSolve` in `live_glue.rs` for why they are told apart).
#[derive(Debug, Clone, Copy, Default)]
struct Phases {
    on_hart0: PhaseCounters,
    critical: PhaseCounters,
}

impl Phases {
    fn add(&mut self, on_hart0: PhaseCounters, critical: PhaseCounters) {
        self.on_hart0 = self.on_hart0.saturating_add(on_hart0);
        self.critical = self.critical.saturating_add(critical);
    }
}

/// A measuring build's choice (`DEFORM_STEP_PHASE=rotate cargo xtask firmware`): frame k of a
/// session reports in its `cycles`, instead of the whole step's cost, the critical path of
/// phase k mod 13 of [`PHASES`] (0: the whole step), so that one run breaks a step's cost down
/// by phase in exact counts (docs/PERFORMANCE.md, "The dynamic step by phase"). Unset in every
/// normal build.
const STEP_PHASE: Option<&str> = option_env!("DEFORM_STEP_PHASE");

/// The phases a measuring build reports, in the step's order (`iteration`, the solve's first
/// iteration, is part of `solve`, which also holds its set-up and closing check; so are the
/// solve's MVU phases, `iteration_mvu` the first iteration's and `other_mvu` the rest).
const PHASES: [&str; 13] = [
    "step",
    "ku",
    "rhs_plan",
    "rhs_pass",
    "tool_rows",
    "predict",
    "residual",
    "solve",
    "iteration",
    "iteration_mvu",
    "other_mvu",
    "force",
    "advance",
];

/// The step's cost at the end of each phase, for [`STEP_PHASE`].
#[derive(Default)]
struct PhaseProbe {
    /// The cost when the last phase ended.
    last: PhaseCounters,
    /// Each phase's own cost, in [`PHASES`]' order.
    costs: [PhaseCounters; PHASES.len()],
}

impl PhaseProbe {
    /// Phase `phase` ended with the step's cost at `cost()`. Nothing in a normal build (the
    /// clock is not even read).
    fn mark(&mut self, phase: &str, cost: impl FnOnce() -> PhaseCounters) {
        if STEP_PHASE.is_none() {
            return;
        }
        let cost = cost();
        self.set(phase, cost.saturating_sub(self.last));
        self.last = cost;
    }

    /// Phase `phase` (within another) cost `cost`.
    fn set(&mut self, phase: &str, cost: PhaseCounters) {
        if STEP_PHASE.is_none() {
            return;
        }
        if let Some(k) = PHASES.iter().position(|&p| p == phase) {
            self.costs[k] = cost;
        }
    }

    /// What frame `frame` reports: the whole step's `cost`, or in a measuring build one
    /// phase's (0 where the step did not run it).
    fn report(&self, frame: u32, cost: PhaseCounters) -> PhaseCounters {
        let phase = frame as usize % PHASES.len();
        match STEP_PHASE {
            Some("rotate") if phase != 0 => self.costs[phase],
            _ => cost,
        }
    }
}

/// A real multiplier as a fixed-point integer m·2^−shift (m below 2^40, so a 21-bit raw value
/// times it stays within `i64`).
#[derive(Debug, Clone, Copy, Default)]
struct Fixed {
    m: i64,
    shift: i32,
}

impl Fixed {
    fn of(v: f64) -> Fixed {
        if v == 0.0 || !v.is_finite() {
            return Fixed::default();
        }
        let shift = 39 - deform_shared::qformat::floor_log2(v);
        let r = ldexp(v, shift);
        Fixed {
            m: (if r >= 0.0 { r + 0.5 } else { r - 0.5 }) as i64,
            shift,
        }
    }

    /// raw·m·2^−shift, rounded to nearest.
    fn times(self, raw: i32) -> i64 {
        crate::predict::scale(i64::from(raw) * self.m, self.shift)
    }
}

/// b₀ at the rows a tool node writes (its own and its couplings'), per direction, kept on hart
/// 0 while pass B overwrites b: at most every tool node and its row.
type Stash = heapless::Vec<StashRow, { MAX_TOOL_NODES * (MAX_TOOL_ROW + 1) }>;

/// One row of the [`Stash`]: its index, b₀ there per direction, and which tool terms write it.
#[derive(Debug, Clone, Copy)]
struct StashRow {
    row: u32,
    old: [i32; MAX_DIRECTIONS],
    writer: Writer,
}

/// Which tool terms write a stashed row, found once while the stash is built so that
/// [`Session::tool_rows`] does not search every tool's row for every stashed row (a quadratic
/// search that cost more than the rows' arithmetic).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Writer {
    /// Tool `t`'s own row: S_tt·v₁t, whatever else couples to it.
    Own(u8),
    /// Only tool `t` couples to it, first at position `k` of its row.
    Single { t: u8, k: u8 },
    /// Several tools couple to it: every tool's row is searched, as in the general case.
    Many,
}

/// Whether a tool row's node and columns are all distinct, told cheaply: the columns rise
/// strictly and none is the node.
fn distinct_rows(r: &ToolRow) -> bool {
    r.row.windows(2).all(|w| w[0].column < w[1].column) && r.row.iter().all(|c| c.column != r.node)
}

impl Writer {
    /// The writer of a row first stashed with `self` and met again with `later`. Nodes are
    /// distinct (`DuplicateNode`), so at most one tool owns a row; a row repeated within one
    /// tool's couplings keeps its first position (the one a search finds).
    fn and(self, later: Writer) -> Writer {
        match (self, later) {
            (Writer::Own(t), _) | (_, Writer::Own(t)) => Writer::Own(t),
            (Writer::Single { t, k }, Writer::Single { t: t2, .. }) if t == t2 => {
                Writer::Single { t, k }
            }
            _ => Writer::Many,
        }
    }
}

/// One active direction of a step: its index and what its passes planned and measured.
#[derive(Debug, Clone, Copy)]
struct Step {
    d: usize,
    plan: RhsPlan,
    sums: RhsSums,
    terms: ToolTerms,
    /// v₀'s block before the start's extrapolation.
    v0: Block,
    /// What this step keeps for the next one (where the last solve left a bounded r).
    kept: Option<Kept>,
    /// A bound on ‖ε_start − ε₀‖ (the start's error less r₀f's, [`Stepping::delta`]);
    /// infinite without a bounded start.
    delta: Upper,
    /// The start is v₀ + Δv₀ ([`crate::dynamics::Stepping::start_history`]), decided once by
    /// pass A for pass D too.
    extrapolate: bool,
}

/// The bound of pass A's rounding of v₀ + Δv₀ in halves of a unit of its result's exponent
/// ([`crate::cg::update_error`]), from v's block after (`v`) and before (`v0`) it: v₀'s own
/// term is floored where the result's exponent rose above v₀'s.
fn pass_a_halves(v: Block, v0: Block) -> u64 {
    if v.e > v0.e {
        4
    } else {
        2
    }
}

/// Records [`start_drift`]'s terms (real units) for a host measurement ([`crate::trace`]):
/// "start" = [2·e0, r₋₁f's drift, √n·d₁'s rounding, √n·d₀'s, √n·pass D's shifts,
/// √n·‖S‖∞·Δv's rounding, √n·‖S‖∞·pass A's, the whole bound, steps unchecked,
/// ‖ε₀ − ε₋₁‖'s bound], the history's terms 0 without one.
#[cfg(feature = "testkit")]
fn trace_start(
    (root_n, s_inf): (Upper, Upper),
    (e_d, e): (i32, i32),
    e0: Upper,
    extrapolated: Option<(&crate::dynamics::History, i32, u64)>,
    (drift, unchecked): (Upper, u32),
    delta: Upper,
) {
    let f = |u: Upper| u.to_f64();
    let rn = f(root_n);
    let d1 = rn * f(Upper::small(1, e_d));
    let mut v = [0f64; 10];
    v[9] = f(delta);
    v[2] = d1;
    v[7] = f(drift);
    v[8] = f64::from(unchecked);
    match extrapolated {
        None => {
            v[0] = f(e0);
            v[4] = rn * f(Upper::small(1, e));
        }
        Some((h, e_x, a_halves)) => {
            v[0] = 2.0 * f(e0);
            v[1] = f(h.r1_drift);
            v[3] = rn * f(h.d0_err);
            v[4] = rn * f(Upper::small(2, e));
            v[5] = rn * f(s_inf) * f(Upper::small(1, h.dv.e));
            v[6] = rn * f(s_inf) * f(Upper::small(a_halves, e_x - 1));
        }
    }
    crate::trace::record("start", &v);
}

/// Per lane, pass D's plan and the bound the solve may rely on ([`Session::plan_starts`]).
type Starts = (
    [Option<ResidualPlan>; MAX_DIRECTIONS],
    [Option<Upper>; MAX_DIRECTIONS],
);

/// What a step keeps for the next one's extrapolated start ([`History`]): d₁'s narrowed block
/// and its error bound (real units, per element), r₀f's block and its drift.
#[derive(Debug, Clone, Copy)]
struct Kept {
    d: Block,
    r: Block,
    d_err: Upper,
    r_drift: Upper,
}

/// A step's tool terms, which [`Session::plan_rhs`] forms before the step's plan (which needs
/// them).
#[derive(Debug, Clone, Copy, Default)]
struct ToolTerms {
    /// Per tool node, what its couplings' raw values of S and K are multiplied by on the rows
    /// they couple to, in b's (the resident S's) units: v₁t·2^−F_S, and h·u₀t·2^−F_K with
    /// the scales of S and K folded in (the resident K lacks the tool's columns).
    s_mult: [f64; MAX_TOOL_NODES],
    k_mult: [f64; MAX_TOOL_NODES],
    /// Per tool node, (K·u₀)_t and m·v₀t (real units), for the force.
    ku: [f64; MAX_TOOL_NODES],
    mv: [f64; MAX_TOOL_NODES],
}

impl<E: Executor> Session<'_, E> {
    /// Starts K's values into the stiffness copy: the resident words, whose values `UpdateValues`
    /// then replaces.
    pub(super) fn begin_stiffness(&mut self, frac_bits: u8) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        if frac_bits > MAX_FRAC_BITS {
            return Err(ErrorCode::BadFracBits(frac_bits));
        }
        let words = to_usize(shape.words);
        let (Some(src), Some(dst)) = (
            self.store.words.get(..words),
            self.store.stiffness.get_mut(..words),
        ) else {
            return Err(ErrorCode::TooManyWords {
                requested: shape.words,
                capacity: to_u32(self.store.stiffness.len()),
            });
        };
        dst.copy_from_slice(src);
        self.dynamic.clear();
        self.stiffness = StiffnessState::Updating { frac_bits, done: 0 };
        Ok(Response::Ack)
    }

    /// K's values `offset..offset + values.len()`, as `UpdateValues` does for the matrix.
    pub(super) fn stiffness_values(
        &mut self,
        offset: u32,
        values: &[i32],
    ) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        let StiffnessState::Updating { frac_bits, done } = self.stiffness else {
            return Err(out_of_order(SessionStep::NoUpdate));
        };
        let end = chunk_end(done, offset, values.len(), shape.words)?;
        replace_values(
            self.store
                .stiffness
                .get_mut(to_usize(offset)..to_usize(end)),
            values,
        )?;
        self.stiffness = StiffnessState::Updating {
            frac_bits,
            done: end,
        };
        Ok(Response::Ack)
    }

    /// Ends K's values: complete, and the CRC of K's words as they now are.
    pub(super) fn end_stiffness(&mut self, crc32: u32) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        let StiffnessState::Updating { frac_bits, done } = self.stiffness else {
            return Err(out_of_order(SessionStep::NoUpdate));
        };
        if done != shape.words {
            return Err(out_of_order(SessionStep::UpdateIncomplete));
        }
        let computed = words_crc(self.store.stiffness.get(..to_usize(done)).unwrap_or(&[]));
        if computed != crc32 {
            self.stiffness = StiffnessState::Empty;
            return Err(ErrorCode::MatrixCrc { computed });
        }
        self.stiffness = StiffnessState::Complete { frac_bits };
        Ok(Response::Ack)
    }

    pub(super) fn dynamic_tool(&mut self, tool: DynamicTool) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        self.live.clear();
        self.dynamic.add_tool(tool, shape.n)?;
        Ok(Response::Ack)
    }

    /// Starts the session at rest: u = v = b = r = 0 in every direction, the tool at 0.
    pub(super) fn dynamic_start(&mut self, params: DynamicParams) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        if !matches!(self.stiffness, StiffnessState::Complete { .. }) {
            return Err(dynamic(DynamicError::NoStiffness));
        }
        let n = to_usize(shape.n);
        self.live.clear();
        self.dynamic.start(params)?;
        for (d, v) in self.store.directions.iter_mut().enumerate() {
            for vector in [&mut v.b, &mut v.x, &mut v.x0, &mut v.r] {
                vector.get_mut(..n).ok_or(ErrorCode::ChunkTooLong)?.fill(0);
            }
            self.rhs[d] = VectorState::Complete { exponent: 0 };
            self.guess[d] = VectorState::Empty;
            self.solution[d] = Some(0);
            self.kept[d] = None;
        }
        Ok(Response::Ack)
    }

    /// One step with the tool at `tool` at its end (see [`crate::dynamics`]).
    pub(super) fn dynamic_frame(&mut self, tool: &[[f32; 3]]) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        let t0 = self.exec.now();
        let (tools, st) = self.dynamic.parts().map_err(dynamic)?;
        if tool.len() != tools.len() {
            return Err(ErrorCode::Live(LiveError::ToolCount {
                expected: tools.len() as u8,
                got: tool.len() as u8,
            }));
        }
        if !tool.iter().flatten().all(|u| u.is_finite()) {
            return Err(ErrorCode::Live(LiveError::NotFinite));
        }
        let moved = |d: usize| tool.iter().zip(&st.tool_u).any(|(a, b)| a[d] != b[d]);
        let active: heapless::Vec<usize, MAX_DIRECTIONS> = (0..MAX_DIRECTIONS)
            .filter(|&d| moved(d) || st.u_bound[d] != 0 || st.v[d].bound != 0)
            .collect();
        let mut phases = Phases::default();
        let mut force = [0f64; 3];
        let (mut residual, mut iterations) = (0f64, 0u32);
        // The step's cost so far: hart 0's clock with each parallel phase's critical path in
        // place of its wall time.
        let cost = |exec: &E, phases: &Phases| {
            exec.now()
                .since(t0)
                .saturating_sub(phases.on_hart0)
                .saturating_add(phases.critical)
        };
        let mut probe = PhaseProbe::default();
        if !active.is_empty() {
            self.stiffness_product(shape, &active, &mut phases)?;
            probe.mark("ku", || cost(&self.exec, &phases));
            // b₁ and d = b₁ − b₀ of every active direction (d in Kp's lane): planned, pass B on
            // every hart, the tool rows on hart 0.
            let mut stash = Stash::new();
            let mut steps = heapless::Vec::new();
            self.plan_rhs(shape, tool, &active, &mut stash, &mut steps)?;
            probe.mark("rhs_plan", || cost(&self.exec, &phases));
            let n = to_usize(shape.n);
            self.rhs_pass(n, &mut steps, &mut phases)?;
            probe.mark("rhs_pass", || cost(&self.exec, &phases));
            self.tool_rows(&mut steps, &stash)?;
            probe.mark("tool_rows", || cost(&self.exec, &phases));
            self.predict(n, &mut steps, &mut phases)?;
            probe.mark("predict", || cost(&self.exec, &phases));
            let r_start = self.start_residuals(n, &mut steps, &mut phases)?;
            probe.mark("residual", || cost(&self.exec, &phases));
            let (report, outcomes) = self.solve_step(shape, &mut steps, r_start, &mut phases)?;
            probe.mark("solve", || cost(&self.exec, &phases));
            probe.set("iteration", report.per_iteration.critical());
            // The first iteration's MVU phase, and the solve's other MVU phases (the closing
            // check's pass in a one-iteration step).
            let mvu = report.per_iteration.mvu_critical;
            probe.set("iteration_mvu", mvu);
            probe.set(
                "other_mvu",
                report.whole_solve.mvu_critical.saturating_sub(mvu),
            );
            residual = report.residual;
            iterations = report.iterations;
            for step in &mut steps {
                force[step.d] = self.tool_force(shape, step, outcomes[step.d]);
            }
            probe.mark("force", || cost(&self.exec, &phases));
            self.advance(shape, tool, &steps, &mut phases)?;
            probe.mark("advance", || cost(&self.exec, &phases));
        }
        let (_, st) = self.dynamic.parts().map_err(dynamic)?;
        for (a, b) in st.tool_u.iter_mut().zip(tool) {
            *a = *b;
        }
        st.field_exponent = None;
        if !force.iter().all(|&v| (v as f32).is_finite()) {
            return Err(ErrorCode::Live(LiveError::NotFinite));
        }
        st.frames = st.frames.wrapping_add(1);
        let cost = probe.report(st.frames, cost(&self.exec, &phases));
        let (cycles, stall_cycles) = live_glue::live_counts(cost);
        Ok(Response::LiveFrame(FrameReport {
            force: force.map(|v| v as f32),
            residual: residual as f32,
            iterations: iterations.min(u32::from(u16::MAX)) as u16,
            cycles,
            stall_cycles,
        }))
    }

    /// K·u₀ of the active directions with a displaced state, into Kp's lanes (one per active
    /// direction, in order): one MVU pass over the stiffness copy.
    fn stiffness_product(
        &mut self,
        shape: Shape,
        active: &[usize],
        phases: &mut Phases,
    ) -> Result<(), ErrorCode> {
        let (_, st) = self.dynamic.parts().map_err(dynamic)?;
        if active.iter().all(|&d| st.u_bound[d] == 0) {
            // u = 0: so is K·u₀ (Kp's lanes are not read then: pass B's term on them is 0).
            st.ku_or = [0; 3];
            return Ok(());
        }
        let StiffnessState::Complete { frac_bits } = self.stiffness else {
            return Err(dynamic(DynamicError::NoStiffness));
        };
        let n = to_usize(shape.n);
        let plan = self
            .plan
            .as_ref()
            .ok_or(out_of_order(SessionStep::NoMatrix))?;
        let Parts {
            matrix,
            work,
            directions,
        } = self
            .store
            .parts(shape, Words::Stiffness { frac_bits }, plan)?;
        let mut us: heapless::Vec<&mut [i32], MAX_DIRECTIONS> = heapless::Vec::new();
        for (d, v) in directions.iter_mut().enumerate() {
            if active.contains(&d) {
                let _ = us.push(v.x.get_mut(..n).ok_or(ErrorCode::ChunkTooLong)?);
            }
        }
        let product = cg::product(&matrix, &mut us, work, &self.exec).map_err(ErrorCode::Solve)?;
        phases.add(product.on_hart0, product.critical);
        let (_, st) = self.dynamic.parts().map_err(dynamic)?;
        // Each lane's OR, which pass B plans with.
        for (lane, &d) in active.iter().enumerate() {
            st.ku_or[d] = product.or[lane];
        }
        Ok(())
    }

    /// The tool's velocities and force terms and pass B's plans of every active direction into
    /// `steps`, and b₀ at the tool's rows into `stash`, which pass B ([`Self::rhs_pass`]) then
    /// overwrites and the tool rows ([`Self::tool_rows`]) read. (Both are the caller's: at
    /// 4 kB and 1.3 kB, returning them by value cost more copying than the rows' work.)
    fn plan_rhs(
        &mut self,
        shape: Shape,
        tool: &[[f32; 3]],
        active: &[usize],
        stash: &mut Stash,
        steps: &mut heapless::Vec<Step, MAX_DIRECTIONS>,
    ) -> Result<(), ErrorCode> {
        let (n, f_s) = (to_usize(shape.n), i32::from(shape.frac_bits));
        let StiffnessState::Complete { frac_bits } = self.stiffness else {
            return Err(dynamic(DynamicError::NoStiffness));
        };
        let magnitudes: heapless::Vec<[f64; 2], MAX_TOOL_NODES> =
            self.dynamic.row_magnitudes().iter().copied().collect();
        let (tools, st) = self.dynamic.parts().map_err(dynamic)?;
        // K's raw values are K·2^(F − k_scale); b is kept in the resident S's units, b·2^−s_scale.
        let f_k = i32::from(frac_bits) - i32::from(st.params.k_scale);
        let s_scale = i32::from(st.params.s_scale);
        let (h, m) = (f64::from(st.params.h), f64::from(st.params.mass));
        steps.clear();
        let mut sat = 0;
        for &d in active {
            let dir = &self.store.directions[d];
            let (u, v) = (
                dir.x.get(..n).unwrap_or(&[]),
                dir.x0.get(..n).unwrap_or(&[]),
            );
            let (e_u, e_v) = (self.solution[d].unwrap_or(0), st.v[d].e);
            // The tool's terms first; the plan, which needs them, last.
            let mut terms = ToolTerms::default();
            let mut tool_part = 0f64;
            for (t, dt) in tools.iter().enumerate() {
                let node = dt.s.node as usize;
                let u_then = f64::from(st.tool_u[t][d]);
                let velocity = (f64::from(tool[t][d]) - u_then) / h;
                terms.s_mult[t] = ldexp(velocity, -f_s);
                terms.k_mult[t] = ldexp(h * u_then, -f_k - s_scale);
                let own_u = u.get(node).copied().unwrap_or(0);
                terms.ku[t] = ldexp(row_sum(&dt.k, own_u, u) as f64, e_u - f_k);
                terms.mv[t] = m * ldexp(f64::from(v.get(node).copied().unwrap_or(0)), e_v);
                // Σ|q| over the rows of S and K, formed once per tool set.
                let [column_s, column_k] = magnitudes.get(t).copied().unwrap_or_default();
                tool_part += column_s * terms.s_mult[t].abs() + column_k * terms.k_mult[t].abs();
            }
            let e_old = self.rhs[d].exponent(SessionStep::NoRhs)?;
            let plan = RhsPlan::new(
                ldexp(m, -s_scale),
                ldexp(h, -s_scale),
                st.v[d],
                st.ku_or[d],
                e_u - f_k,
                tool_part,
                e_old,
                &mut sat,
            );
            let _ = steps.push(Step {
                d,
                plan,
                sums: RhsSums::default(),
                terms,
                v0: st.v[d],
                kept: None,
                delta: Upper::INFINITE,
                extrapolate: false,
            });
        }
        if sat != 0 {
            return Err(ErrorCode::Solve(SolveFailure::NotPositiveDefinite {
                iteration: 0,
            }));
        }
        // b₀ at the tool's rows, before pass B overwrites it, and who writes each row.
        stash.clear();
        for (t, dt) in tools.iter().enumerate() {
            let t = t as u8;
            let rows = core::iter::once((dt.s.node, Writer::Own(t))).chain(
                (dt.s.row.iter().enumerate())
                    .map(|(k, c)| (c.column, Writer::Single { t, k: k as u8 })),
            );
            // The first tool's rows need no search where its columns rise strictly and skip
            // its node (the host sends them so, in its CSR's order): none can repeat.
            let fresh = stash.is_empty() && distinct_rows(&dt.s);
            for (row, writer) in rows {
                let seen = (!fresh)
                    .then(|| stash.iter_mut().find(|e| e.row == row))
                    .flatten();
                if let Some(entry) = seen {
                    entry.writer = entry.writer.and(writer);
                    continue;
                }
                let old = core::array::from_fn(|d| {
                    let b = &self.store.directions[d].b;
                    b.get(row as usize).copied().unwrap_or(0)
                });
                let _ = stash.push(StashRow { row, old, writer });
            }
        }
        Ok(())
    }

    /// Pass B of every active direction on every hart's share.
    fn rhs_pass(
        &mut self,
        n: usize,
        steps: &mut [Step],
        phases: &mut Phases,
    ) -> Result<(), ErrorCode> {
        let harts = self.pass_harts();
        let mut sums = [[RhsSums::default(); MAX_DIRECTIONS]; MAX_HARTS];
        let words = cg::sum_words_for(&self.exec, steps.len());
        with_sum_words!(words, |R| {
            let Storage { directions, kp, .. } = &mut self.store;
            if kp.len() < n {
                return Err(ErrorCode::ChunkTooLong);
            }
            let kp = SharedSlice::new(sum_rows::<R>(kp, n));
            let mut bs: [&mut [i32]; MAX_DIRECTIONS] = Default::default();
            let mut vs: [&[i32]; MAX_DIRECTIONS] = Default::default();
            for (d, v) in directions.iter_mut().enumerate() {
                bs[d] = v.b.get_mut(..n).ok_or(ErrorCode::ChunkTooLong)?;
                vs[d] = v.x0.get(..n).ok_or(ErrorCode::ChunkTooLong)?;
            }
            let bs = bs.map(SharedSlice::new);
            let out = SharedSlice::new(&mut sums);
            let steps = &*steps;
            let task = |h: usize| {
                let range = share(n, harts, h);
                for (lane, step) in steps.iter().enumerate() {
                    // SAFETY: each hart writes only its own share of b and Kp and its own
                    // slot of the sums; v is only read.
                    unsafe {
                        out.slice_mut(h..h + 1)[0][lane] = rhs_share(
                            bs[step.d].slice_mut(range.clone()),
                            kp.slice_mut(range.clone()),
                            &vs[step.d][range.clone()],
                            lane,
                            &step.plan,
                        );
                    }
                }
            };
            let t = self.exec.now();
            let counts = self.exec.run_measured(harts, &task);
            let critical = slowest(&counts[..harts]);
            phases.add(self.exec.now().since(t), critical);
        });
        for (lane, step) in steps.iter_mut().enumerate() {
            for hart in &sums[..harts] {
                let s = hart[lane];
                step.sums.bb += s.bb;
                step.sums.b_or |= s.b_or;
                step.sums.d_or |= s.d_or;
            }
        }
        Ok(())
    }

    /// The tool's rows of every active direction on hart 0: b₁ᵢ −= S_it·v₁t where a tool node
    /// couples, b₁t = S_tt·v₁t at its own row; d, Σb² and the ORs follow.
    fn tool_rows(&mut self, steps: &mut [Step], stash: &Stash) -> Result<(), ErrorCode> {
        let tools = self.dynamic.tools();
        // Kp's rows as K·u₀ laid them out: row i's lane is word `words·i + lane`.
        let words = cg::sum_words_for(&self.exec, steps.len());
        for (lane, step) in steps.iter_mut().enumerate() {
            let b = &mut self.store.directions[step.d].b;
            let kp = self.store.kp.as_flattened_mut();
            // Per tool node, its couplings' multipliers in b's units as fixed-point integers:
            // a raw value times one is a product and a rounded shift, no soft float per row.
            let e = step.plan.e;
            // Only the tools there are: each is a soft-float multiply and more.
            let fixed = |mult: &[f64; MAX_TOOL_NODES], t: usize| {
                if t < tools.len() {
                    Fixed::of(ldexp(mult[t], -e))
                } else {
                    Fixed::default()
                }
            };
            let ms: [Fixed; MAX_TOOL_NODES] =
                core::array::from_fn(|t| fixed(&step.terms.s_mult, t));
            let mk: [Fixed; MAX_TOOL_NODES] =
                core::array::from_fn(|t| fixed(&step.terms.k_mult, t));
            // Tool t's coupling at position k of its row: S's and K's terms.
            let coupling = |t: usize, k: usize| {
                let (s, k_row) = (&tools[t].s.row, &tools[t].k.row);
                let ks = k_row.get(k).map_or(0, |c| c.value);
                ms[t].times(s[k].value) + mk[t].times(ks)
            };
            for entry in stash {
                let (row, old) = (entry.row, entry.old);
                let i = row as usize;
                let Some(bi) = b.get_mut(i) else { continue };
                let formed = *bi;
                let mut value = i64::from(formed);
                match entry.writer {
                    // A tool node's own row: S_tt·v₁t, whatever else couples to it.
                    Writer::Own(t) => value = ms[t as usize].times(tools[t as usize].s.diagonal),
                    Writer::Single { t, k } => value -= coupling(t as usize, k as usize),
                    Writer::Many => {
                        for (t, dt) in tools.iter().enumerate() {
                            if let Some(k) = dt.s.row.iter().position(|c| c.column == row) {
                                value -= coupling(t, k);
                            }
                        }
                    }
                }
                let value = value.clamp(-(1 << 30) + 1, (1 << 30) - 1) as i32;
                *bi = value;
                let sq = |z: i32| (i64::from(z) * i64::from(z)) as u128;
                step.sums.bb = step.sums.bb - sq(formed) + sq(value);
                step.sums.b_or |= magnitude_bits(value);
                let d = step.plan.change(value, old[step.d]);
                if let Some(k) = kp.get_mut(words * i + lane) {
                    *k = d;
                }
                step.sums.d_or |= (d ^ (d >> 63)) as u64;
            }
            self.rhs[step.d] = VectorState::Complete {
                exponent: step.plan.e,
            };
        }
        Ok(())
    }

    /// The start's residual r₀ = d + r (pass R, where the last solve left a checked r), then
    /// the fused solve S·v₁ = b₁ of the active directions from v₀ (x0), v₁'s and r's state
    /// kept.
    fn solve_step(
        &mut self,
        shape: Shape,
        steps: &mut [Step],
        r_start: [Option<GivenResidual>; MAX_DIRECTIONS],
        phases: &mut Phases,
    ) -> Result<(SolveReport, [Outcome; MAX_DIRECTIONS]), ErrorCode> {
        let n = to_usize(shape.n);
        let (_, st) = self.dynamic.parts().map_err(dynamic)?;
        let params = SolveParams {
            max_iterations: st.params.max_iterations,
            tolerance: f64::from(st.params.tolerance),
            start: Start::Previous,
            directions: steps.len() as u8,
            cycle_budget: st.params.cycle_budget,
        };
        let v_exponents = st.v.map(|b| b.e);
        let plan = self
            .plan
            .as_ref()
            .ok_or(out_of_order(SessionStep::NoMatrix))?;
        let Parts {
            matrix,
            work,
            directions,
        } = self.store.parts(shape, Words::Resident, plan)?;
        let mut systems: heapless::Vec<System<'_>, MAX_DIRECTIONS> = heapless::Vec::new();
        for (d, v) in directions.iter_mut().enumerate() {
            let Some(lane) = steps.iter().position(|s| s.d == d) else {
                continue;
            };
            let (Some(b), Some(x), Some(r)) = (v.b.get(..n), v.x0.get_mut(..n), v.r.get_mut(..n))
            else {
                return Err(ErrorCode::ChunkTooLong);
            };
            let _ = systems.push(System {
                b,
                b_exponent: steps[lane].plan.e,
                x,
                x_exponent: v_exponents[d],
                r,
                r_start: r_start[d],
                outcome: Outcome::default(),
            });
        }
        let report = cg::solve(&matrix, &mut systems, work, &params, &self.exec)
            .map_err(ErrorCode::Solve)?;
        let (on_hart0, critical) = live_glue::solve_cost(&report);
        phases.add(on_hart0, critical);
        let mut outcomes = [Outcome::default(); MAX_DIRECTIONS];
        let (_, st) = self.dynamic.parts().map_err(dynamic)?;
        for (step, system) in steps.iter().zip(&systems) {
            let d = step.d;
            outcomes[d] = system.outcome;
            st.v[d] = Block {
                e: system.x_exponent,
                bound: system.outcome.x_bound,
            };
            let o = system.outcome;
            // The next step starts from r wherever its drift is bounded: an exact pass's, or a
            // recursive r the solve carried the bound of.
            st.residual[d] = (o.r_exact || o.drift.is_finite()).then_some(Block {
                e: o.r_exponent,
                bound: o.r_bound,
            });
            // r₁ − r₀f's error: the start's less r₀f's, plus the updates' (the updates' sum is
            // infinite where an exact pass replaced r), or else at most both drifts.
            st.delta[d] = if o.updates.is_finite() {
                step.delta.plus(o.updates)
            } else {
                o.drift.plus(st.drift[d])
            };
            st.drift[d] = o.drift;
            st.unchecked[d] = if o.r_exact {
                0
            } else {
                st.unchecked[d].saturating_add(1)
            };
        }
        Ok((report, outcomes))
    }

    /// The harts a dynamic step's O(n) passes split their rows over: the plan's MVUs, or one
    /// without a plan (the passes then run on hart 0 alone).
    fn pass_harts(&self) -> usize {
        self.plan.as_ref().map_or(1, |p| p.mvus).clamp(1, MAX_HARTS)
    }

    /// Whether the spare storage (the live loop's response columns, unused by a dynamic
    /// session) holds every direction's history: four vectors each.
    fn history_room(&self, n: usize) -> bool {
        self.store.responses.len() >= 4 * MAX_DIRECTIONS * n
    }

    /// History vector `k` of direction `d` (0: Δv, 1: v₀, 2: d, 3: r), as a `SharedSlice`
    /// base index into the spare storage.
    fn history_at(n: usize, d: usize, k: usize) -> core::ops::Range<usize> {
        let start = (4 * d + k) * n;
        start..start + n
    }

    /// Pass A on every hart: v₀ kept (history slot 1), and where the history holds Δv₀ the
    /// start v₀ + Δv₀ in x0 (u₁ ≈ u₀ + h·(2v₀ − v₋₁)), v's block updated.
    fn predict(
        &mut self,
        n: usize,
        steps: &mut [Step],
        phases: &mut Phases,
    ) -> Result<(), ErrorCode> {
        if !self.history_room(n) {
            return Ok(());
        }
        let harts = self.pass_harts();
        let (_, st) = self.dynamic.parts().map_err(dynamic)?;
        let mut sat = 0;
        for step in steps.iter_mut() {
            step.extrapolate = st
                .start_history(step.d, (step.sums.bb, step.plan.e))
                .is_some();
        }
        let steps = &*steps;
        let lins: [Option<Lin>; MAX_DIRECTIONS] = core::array::from_fn(|lane| {
            let step = steps.get(lane).filter(|s| s.extrapolate)?;
            let h = st.history[step.d]?;
            Some(Lin::new(
                Scalar::ONE,
                h.dv,
                false,
                Some(st.v[step.d]),
                &mut sat,
            ))
        });
        let mut ors = [[0u32; MAX_DIRECTIONS]; MAX_HARTS];
        {
            let Storage {
                directions,
                responses,
                ..
            } = &mut self.store;
            let spare = SharedSlice::new(responses);
            let mut vs: [&mut [i32]; MAX_DIRECTIONS] = Default::default();
            for (d, v) in directions.iter_mut().enumerate() {
                vs[d] = v.x0.get_mut(..n).ok_or(ErrorCode::ChunkTooLong)?;
            }
            let vs = vs.map(SharedSlice::new);
            let out = SharedSlice::new(&mut ors);
            let lins = &lins;
            let task = |h: usize| {
                let range = share(n, harts, h);
                for (lane, step) in steps.iter().enumerate() {
                    let (d, lo, hi) = (step.d, range.start, range.end);
                    let at = |k| Self::history_at(n, d, k);
                    // SAFETY: each hart touches only its own share of v and of the history
                    // vectors (disjoint ranges of the spare storage), and its own slot.
                    unsafe {
                        let v0 = spare.slice_mut(at(1).start + lo..at(1).start + hi);
                        let dv = &spare.as_slice()[at(0).start + lo..at(0).start + hi];
                        out.slice_mut(h..h + 1)[0][lane] = predict_share(
                            vs[d].slice_mut(range.clone()),
                            v0,
                            dv,
                            lins[lane].as_ref(),
                        );
                    }
                }
            };
            let t = self.exec.now();
            let counts = self.exec.run_measured(harts, &task);
            let critical = slowest(&counts[..harts]);
            phases.add(self.exec.now().since(t), critical);
        }
        let (_, st) = self.dynamic.parts().map_err(dynamic)?;
        for (lane, step) in steps.iter().enumerate() {
            if let Some(lin) = lins[lane] {
                let or = ors[..harts].iter().fold(0, |o, s| o | s[lane]);
                st.v[step.d] = Block {
                    e: lin.e,
                    bound: bound_of(or),
                };
            }
        }
        Ok(())
    }

    /// Pass D's plan for every active direction whose last solve left a bounded r, what the
    /// step keeps for the next one, and the bound of the start's residual
    /// ([`start_drift`]) where the solve may rely on it.
    fn plan_starts(&mut self, n: usize, steps: &mut [Step]) -> Result<Starts, ErrorCode> {
        let room = self.history_room(n);
        let (s_inf, root_n) = self.s_inf();
        let (_, st) = self.dynamic.parts().map_err(dynamic)?;
        let mut plans = [None; MAX_DIRECTIONS];
        let mut drifts = [None; MAX_DIRECTIONS];
        let mut sat = 0;
        for (lane, step) in steps.iter_mut().enumerate() {
            let Some(r) = st.residual[step.d] else {
                continue;
            };
            let history = st.history[step.d].filter(|_| room && step.extrapolate);
            let extrapolated = history.map(|h| (h.d0, h.r1));
            let plan = ResidualPlan::new(step.sums.d_or, step.plan.e_d, r, extrapolated, &mut sat);
            let (_, _, d_bound) = Narrow::new(bound_of_u64(step.sums.d_or), &mut sat);
            let d = Block {
                e: plan.e_keep,
                bound: d_bound,
            };
            step.kept = room.then_some(Kept {
                d,
                r,
                d_err: Upper::small(1, plan.e_keep).plus(Upper::small(1, step.plan.e_d)),
                r_drift: st.drift[step.d],
            });
            let e0 = st.drift[step.d];
            let local = start_local(
                root_n,
                s_inf,
                (step.plan.e_d, plan.e),
                history
                    .as_ref()
                    .map(|h| (h, st.v[step.d].e, pass_a_halves(st.v[step.d], step.v0))),
            );
            // ε_start − ε₀ is (ε₀ − ε₋₁) plus the start's roundings (extrapolated) or those
            // alone (from v₀): the next step's `delta` before this solve's updates.
            // Either bound of ‖ε₀ − ε₋₁‖ holds; the carried one where there is one (a branch
            // instead of a sum and a comparison on hart 0's serial path).
            let step_delta = match history {
                Some(_) if st.delta[step.d].is_finite() => st.delta[step.d],
                Some(h) => e0.plus(h.r1_drift),
                None => Upper::ZERO,
            };
            step.delta = step_delta.plus(local);
            let drift = e0.plus(step.delta);
            #[cfg(feature = "testkit")]
            trace_start(
                (root_n, s_inf),
                (step.plan.e_d, plan.e),
                st.drift[step.d],
                history
                    .as_ref()
                    .map(|h| (h, st.v[step.d].e, pass_a_halves(st.v[step.d], step.v0))),
                (drift, st.unchecked[step.d]),
                st.delta[step.d],
            );
            // Past MAX_UNCHECKED steps on the bound alone, or without a finite one, the solve
            // checks its residual by an exact pass.
            drifts[lane] =
                (st.unchecked[step.d] < MAX_UNCHECKED && drift.is_finite()).then_some(drift);
            plans[lane] = Some(plan);
        }
        Ok((plans, drifts))
    }

    /// Pass D on every hart for every active direction whose r the last solve bounded: the
    /// start's residual r₀ = d₁ + r₀f (from v₀) or d₁ + 2·r₀f − d₀ − r₋₁f (from v₀ + Δv₀) in
    /// O(n) instead of an MVU pass ([`residual_share`]), the history kept for the next step.
    fn start_residuals(
        &mut self,
        n: usize,
        steps: &mut [Step],
        phases: &mut Phases,
    ) -> Result<[Option<GivenResidual>; MAX_DIRECTIONS], ErrorCode> {
        let harts = self.pass_harts();
        let room = self.history_room(n);
        let (plans, drifts) = self.plan_starts(n, steps)?;
        let mut out = [None; MAX_DIRECTIONS];
        if plans.iter().all(Option::is_none) {
            return Ok(out);
        }
        let mut sums = [[(0u128, 0u32); MAX_DIRECTIONS]; MAX_HARTS];
        let words = cg::sum_words_for(&self.exec, steps.len());
        with_sum_words!(words, |R| {
            let Storage {
                directions,
                kp,
                responses,
                ..
            } = &mut self.store;
            if kp.len() < n {
                return Err(ErrorCode::ChunkTooLong);
            }
            let kp = SharedSlice::new(sum_rows::<R>(kp, n));
            let spare = SharedSlice::new(responses);
            let mut rs: [&mut [i32]; MAX_DIRECTIONS] = Default::default();
            for (d, v) in directions.iter_mut().enumerate() {
                rs[d] = v.r.get_mut(..n).ok_or(ErrorCode::ChunkTooLong)?;
            }
            let rs = rs.map(SharedSlice::new);
            let out = SharedSlice::new(&mut sums);
            let steps = &*steps;
            let task = |h: usize| {
                let range = share(n, harts, h);
                for (lane, step) in steps.iter().enumerate() {
                    let Some(plan) = plans[lane] else { continue };
                    let (d, lo, hi) = (step.d, range.start, range.end);
                    let at = |k| Self::history_at(n, d, k);
                    // SAFETY: each hart writes only its own share of r and of the history
                    // vectors and its own slot of the sums; Kp is only read.
                    unsafe {
                        let history = room.then(|| {
                            let (d_at, r_at) = (at(2).start, at(3).start);
                            (
                                spare.slice_mut(d_at + lo..d_at + hi),
                                spare.slice_mut(r_at + lo..r_at + hi),
                            )
                        });
                        out.slice_mut(h..h + 1)[0][lane] = residual_share(
                            rs[d].slice_mut(range.clone()),
                            &kp.as_slice()[range.clone()],
                            lane,
                            &plan,
                            history,
                        );
                    }
                }
            };
            let t = self.exec.now();
            let counts = self.exec.run_measured(harts, &task);
            let critical = slowest(&counts[..harts]);
            phases.add(self.exec.now().since(t), critical);
        });
        for (lane, step) in steps.iter().enumerate() {
            let Some(plan) = plans[lane] else { continue };
            let rr: u128 = sums[..harts].iter().map(|s| s[lane].0).sum();
            let or = sums[..harts].iter().fold(0, |o, s| o | s[lane].1);
            out[step.d] = Some(GivenResidual {
                exponent: plan.e,
                rr,
                bound: bound_of(or),
                verify: true,
                drift: drifts[lane],
            });
        }
        Ok(out)
    }

    /// The force the tool exerts in the step's direction: Σ_t ((S·v₁)_t − m·v₀t)/h + (K·u₀)_t.
    fn tool_force(&self, shape: Shape, step: &Step, _outcome: Outcome) -> f64 {
        let (n, f_s) = (to_usize(shape.n), i32::from(shape.frac_bits));
        let v = self.store.directions[step.d].x0.get(..n).unwrap_or(&[]);
        let (Some(st), tools) = (self.dynamic_state(), self.dynamic.tools()) else {
            return 0.0;
        };
        let h = f64::from(st.params.h);
        // S = S_resident·2^s_scale.
        let f_s = f_s - i32::from(st.params.s_scale);
        tools
            .iter()
            .enumerate()
            .map(|(t, dt)| {
                let node = dt.s.node as usize;
                let own = v.get(node).copied().unwrap_or(0);
                let sv = ldexp(row_sum(&dt.s, own, v) as f64, st.v[step.d].e - f_s);
                (sv - step.terms.mv[t]) / h + step.terms.ku[t]
            })
            .sum()
    }

    /// Pass U on every hart, u₁ = u₀ + h·v₁ (and, where there is room, the step's velocity
    /// change for the next step's start), then the tool nodes at their prescribed values.
    fn advance(
        &mut self,
        shape: Shape,
        tool: &[[f32; 3]],
        steps: &[Step],
        phases: &mut Phases,
    ) -> Result<(), ErrorCode> {
        let n = to_usize(shape.n);
        let harts = self.pass_harts();
        let room = self.history_room(n);
        let (tools, st) = self.dynamic.parts().map_err(dynamic)?;
        let nodes: heapless::Vec<usize, MAX_TOOL_NODES> =
            tools.iter().map(|t| t.s.node as usize).collect();
        let h = Scalar::of_f64(f64::from(st.params.h));
        let mut sat = 0;
        let lins: heapless::Vec<Lin, MAX_DIRECTIONS> = steps
            .iter()
            .map(|step| {
                let u = Block {
                    e: self.solution[step.d].unwrap_or(0),
                    bound: st.u_bound[step.d],
                };
                Lin::new(h, st.v[step.d], false, Some(u), &mut sat)
            })
            .collect();
        let diffs: heapless::Vec<Difference, MAX_DIRECTIONS> = steps
            .iter()
            .map(|step| Difference::new(st.v[step.d], step.v0))
            .collect();
        let mut ors = [[(0u32, 0u32); MAX_DIRECTIONS]; MAX_HARTS];
        {
            let Storage {
                directions,
                responses,
                ..
            } = &mut self.store;
            let spare = SharedSlice::new(responses);
            let mut us: [&mut [i32]; MAX_DIRECTIONS] = Default::default();
            let mut vs: [&[i32]; MAX_DIRECTIONS] = Default::default();
            for (d, v) in directions.iter_mut().enumerate() {
                us[d] = v.x.get_mut(..n).ok_or(ErrorCode::ChunkTooLong)?;
                vs[d] = v.x0.get(..n).ok_or(ErrorCode::ChunkTooLong)?;
            }
            let us = us.map(SharedSlice::new);
            let out = SharedSlice::new(&mut ors);
            let (lins, diffs) = (&lins, &diffs);
            let task = |hart: usize| {
                let range = share(n, harts, hart);
                for (lane, step) in steps.iter().enumerate() {
                    let (d, lo, hi) = (step.d, range.start, range.end);
                    let at = |k| Self::history_at(n, d, k);
                    // SAFETY: each hart writes only its own share of u and of the history's Δv
                    // and its own slot; v and v₀ are only read.
                    unsafe {
                        let history = room.then(|| {
                            let (v0_at, dv_at) = (at(1).start, at(0).start);
                            (
                                &spare.as_slice()[v0_at + lo..v0_at + hi],
                                spare.slice_mut(dv_at + lo..dv_at + hi),
                                &diffs[lane],
                            )
                        });
                        out.slice_mut(hart..hart + 1)[0][lane] = advance_share(
                            us[d].slice_mut(range.clone()),
                            &vs[d][range.clone()],
                            &lins[lane],
                            history,
                        );
                    }
                }
            };
            let t = self.exec.now();
            let counts = self.exec.run_measured(harts, &task);
            let critical = slowest(&counts[..harts]);
            phases.add(self.exec.now().since(t), critical);
        }
        for (lane, step) in steps.iter().enumerate() {
            let e = lins[lane].e;
            let u = self.store.directions[step.d]
                .x
                .get_mut(..n)
                .unwrap_or(&mut []);
            let mut or = ors[..harts].iter().fold(0, |o, s| o | s[lane].0);
            for (t, &node) in nodes.iter().enumerate() {
                let r = ldexp(f64::from(tool[t][step.d]), -e);
                let m = (if r >= 0.0 { r + 0.5 } else { r - 0.5 }) as i64;
                if let Some(ui) = u.get_mut(node) {
                    *ui = m.clamp(-(1 << 30) + 1, (1 << 30) - 1) as i32;
                    or |= magnitude_bits(*ui);
                }
            }
            self.solution[step.d] = Some(e);
            st.u_bound[step.d] = if or == 0 { 0 } else { bound_of(or) };
            let dv_or = ors[..harts].iter().fold(0, |o, s| o | s[lane].1);
            // The next step extrapolates only from a checked residual and a kept history.
            st.history[step.d] = match (step.kept, st.residual[step.d]) {
                (Some(kept), Some(_)) if room => Some(History {
                    dv: Block {
                        e: diffs[lane].e,
                        bound: if dv_or == 0 { 0 } else { bound_of(dv_or) },
                    },
                    d0: kept.d,
                    r1: kept.r,
                    d0_err: kept.d_err,
                    r1_drift: kept.r_drift,
                }),
                _ => None,
            };
        }
        Ok(())
    }

    /// ‖S‖∞ of the resident matrix in real units (the solve's) and ⌈√n⌉, for the start's
    /// drift: infinite without a plan, which then bounds nothing.
    fn s_inf(&self) -> (Upper, Upper) {
        match (self.plan.as_ref(), self.loaded()) {
            (Some(plan), Ok(shape)) => plan.drift_norms(to_usize(shape.n), shape.frac_bits),
            _ => (Upper::INFINITE, Upper::INFINITE),
        }
    }

    fn dynamic_state(&self) -> Option<&crate::dynamics::Stepping> {
        self.dynamic.state()
    }
}

#[cfg(test)]
mod tests {
    use super::Writer;

    /// The writer found while stashing equals what searching every tool's row finds: the
    /// owning tool first, else a single coupling tool at its first position, else all.
    #[test]
    fn a_stashed_rows_writer_is_what_a_search_would_find() {
        let single = |t, k| Writer::Single { t, k };
        assert_eq!(single(0, 3).and(Writer::Own(1)), Writer::Own(1));
        assert_eq!(Writer::Own(1).and(single(2, 0)), Writer::Own(1));
        assert_eq!(Writer::Many.and(Writer::Own(2)), Writer::Own(2));
        // A column repeated in one tool's row: the first position stays.
        assert_eq!(single(0, 3).and(single(0, 7)), single(0, 3));
        assert_eq!(single(0, 3).and(single(1, 0)), Writer::Many);
        assert_eq!(Writer::Many.and(single(1, 0)), Writer::Many);
    }
}
