//! The session's live-loop requests (protocol versions 8 and 9, [`deform_shared::live`]): the
//! tool set (displacement rows or force nodes), the local model (Schur sums or compliance),
//! full frames, queries between them and the quantised field. The
//! arithmetic is in [`crate::live`]; this is where it meets the session's vectors and solves.

use deform_shared::live::{
    FieldChunk, FieldSelection, ForceReport, FrameReport, LiveError, LiveParams, ModelReport,
    MotionQuery, MotionReport, ToolRow,
};

use super::*;
use crate::live::{field_exponent, pack_field, Started, ToolKind};
use crate::superpose::{superpose, Column};
use deform_shared::live::MAX_TOOL_NODES;
use deform_shared::protocol::{PhaseCounters, SolveReport};

/// The Schur columns' tolerance: the fixed-point CG's floor, which the host's refinement
/// also uses.
const MODEL_TOLERANCE: f64 = deform_shared::qformat::FIXED_POINT_FLOOR;

fn live(e: LiveError) -> ErrorCode {
    ErrorCode::Live(e)
}

impl<E: Executor> Session<'_, E> {
    pub(super) fn live_tool(&mut self, row: ToolRow) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        self.live.add_tool(row, shape.n).map_err(live)?;
        Ok(Response::Ack)
    }

    /// A force tool at `nodes` (version 9).
    pub(super) fn live_force_tool(&mut self, nodes: &[u32]) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        self.live.set_force_tool(nodes, shape.n).map_err(live)?;
        Ok(Response::Ack)
    }

    /// Starts the live session: one fused CG solve per three tool nodes gives the local
    /// model's columns (Schur sums, or compliance means for a force tool), and the solved
    /// columns themselves are kept as the frames' predictor where they fit
    /// ([`crate::superpose`]). The right-hand sides, solutions and predictions are spent.
    pub(super) fn live_start(&mut self, params: LiveParams) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        let (n, f) = (to_usize(shape.n), i32::from(shape.frac_bits));
        let t0 = self.exec.now();
        self.live.start(params).map_err(live)?;
        let tools = self.live.tools().len();
        let mut report = ModelReport {
            solves: 0,
            iterations: 0,
            cycles: 0,
            converged: true,
            stall_cycles: 0,
        };
        // Hart 0's counts over the solves and their critical paths (see `frame_cost`).
        let (mut counted, mut path) = (PhaseCounters::default(), PhaseCounters::default());
        let mut result = || {
            for first in (0..tools).step_by(MAX_DIRECTIONS) {
                let group = (tools - first).min(MAX_DIRECTIONS);
                for g in 0..group {
                    let (tools, started) = self.live.parts().map_err(live)?;
                    let b = self.store.directions[g]
                        .b
                        .get_mut(..n)
                        .ok_or(ErrorCode::ChunkTooLong)?;
                    let exponent = started.model_rhs(tools, first + g, b, f);
                    self.rhs[g] = VectorState::Complete { exponent };
                }
                let solved = self.solve(&SolveParams {
                    max_iterations: shape.n.saturating_mul(10),
                    tolerance: MODEL_TOLERANCE,
                    start: Start::Zero,
                    directions: group as u8,
                    cycle_budget: 0,
                })?;
                if let Response::Solved(r) = solved {
                    // Each solve counts at its critical path, as a frame's does.
                    let (on_hart0, critical) = solve_cost(&r);
                    counted += on_hart0;
                    path += critical;
                    report.solves += 1;
                    report.iterations += r.iterations;
                    report.converged &= r.converged;
                }
                for g in 0..group {
                    let e_z = self.solution[g].unwrap_or(0);
                    let (tools, started) = self.live.parts().map_err(live)?;
                    let z = self.store.directions[g].x.get(..n).unwrap_or(&[]);
                    started
                        .set_model_column(tools, first + g, z, e_z, f)
                        .map_err(live)?;
                    let held = &mut self.store.responses;
                    hold_column(started, held, tools.len(), first + g, z, e_z);
                }
            }
            Ok(())
        };
        let result = result();
        // The vectors now hold the model's columns, not anything the host sent.
        self.rhs = [VectorState::Empty; MAX_DIRECTIONS];
        self.solution = [None; MAX_DIRECTIONS];
        self.kept = [None; MAX_DIRECTIONS];
        if let Err(e) = result {
            self.live.clear();
            return Err(e);
        }
        let cost = self
            .exec
            .now()
            .since(t0)
            .saturating_sub(counted)
            .saturating_add(path);
        report.cycles = cost.cycles;
        report.stall_cycles = cost.stall_cycles();
        Ok(Response::LiveReady(report))
    }

    /// Checks a frame's or query's tool inputs against the tool set and its kind.
    fn check_tool(&mut self, tool: &[[f32; 3]], kind: ToolKind) -> Result<(), ErrorCode> {
        let (tools, started) = self.live.parts().map_err(live)?;
        if started.kind != kind {
            return Err(live(LiveError::WrongKind));
        }
        if tool.len() != tools.len() {
            return Err(live(LiveError::ToolCount {
                expected: tools.len() as u8,
                got: tool.len() as u8,
            }));
        }
        if !tool.iter().flatten().all(|u| u.is_finite()) {
            return Err(live(LiveError::NotFinite));
        }
        Ok(())
    }

    /// A displacement tool's full frame.
    pub(super) fn live_frame(&mut self, tool: &[[f32; 3]]) -> Result<Response, ErrorCode> {
        let (force, residual, iterations, cost) = self.live_solve(tool, ToolKind::Displacement)?;
        let (cycles, stall_cycles) = live_counts(cost);
        Ok(Response::LiveFrame(FrameReport {
            force,
            residual,
            iterations,
            cycles,
            stall_cycles,
        }))
    }

    /// A force tool's full frame (version 9).
    pub(super) fn live_load(&mut self, load: &[[f32; 3]]) -> Result<Response, ErrorCode> {
        let (displacement, residual, iterations, cost) = self.live_solve(load, ToolKind::Force)?;
        let (cycles, stall_cycles) = live_counts(cost);
        Ok(Response::LiveMotion(MotionReport {
            displacement,
            residual,
            iterations,
            cycles,
            stall_cycles,
        }))
    }

    /// A full frame: right-hand sides from the tool inputs, a fused predicted solve within
    /// the budget, the answer (force or motion), and the local model re-anchored. Returns the
    /// answer, the residual, the iterations and the frame's cost (see [`frame_cost`]).
    fn live_solve(
        &mut self,
        tool: &[[f32; 3]],
        kind: ToolKind,
    ) -> Result<([f32; 3], f32, u16, PhaseCounters), ErrorCode> {
        let shape = self.loaded()?;
        let (n, f) = (to_usize(shape.n), i32::from(shape.frac_bits));
        let t0 = self.exec.now();
        self.check_tool(tool, kind)?;
        let mut exponents = [0i32; MAX_DIRECTIONS];
        for (d, e) in exponents.iter_mut().enumerate() {
            *e = self.rhs[d].exponent(SessionStep::NoRhs)?;
        }
        let params = {
            let (tools, started) = self.live.parts().map_err(live)?;
            for (d, e_b) in exponents.into_iter().enumerate() {
                let b = self.store.directions[d]
                    .b
                    .get_mut(..n)
                    .ok_or(ErrorCode::ChunkTooLong)?;
                started.take_snapshot(d, tools, b, e_b);
                let e = started.patch(d, tools, b, e_b, tool, f).map_err(live)?;
                self.rhs[d] = VectorState::Complete { exponent: e };
            }
            started.params
        };
        let start = self.superpose_start(tool, n)?;
        let Response::Solved(report) = self.solve(&SolveParams {
            max_iterations: params.max_iterations,
            tolerance: f64::from(params.tolerance),
            start,
            directions: MAX_DIRECTIONS as u8,
            cycle_budget: params.cycle_budget,
        })?
        else {
            return Err(out_of_order(SessionStep::NoSolution));
        };
        let (tools, started) = self.live.parts().map_err(live)?;
        let mut answer = [0f64; 3];
        for (d, out) in answer.iter_mut().enumerate() {
            let x = self.store.directions[d].x.get(..n).unwrap_or(&[]);
            let e_x = self.solution[d].unwrap_or(0);
            *out = started.answer(d, tools, x, e_x, tool, f).map_err(live)?;
        }
        if !answer.iter().all(|&v| (v as f32).is_finite()) {
            // An answer no f32 holds is refused, and it anchors nothing.
            return Err(live(LiveError::NotFinite));
        }
        started.anchor(answer, tool);
        let mut base = [[0f32; 3]; MAX_TOOL_NODES];
        for (b, u) in base.iter_mut().zip(tool) {
            *b = *u;
        }
        started.base = Some(base);
        let cost = frame_cost(self.exec.now().since(t0), &report);
        Ok((
            answer.map(|v| v as f32),
            report.residual as f32,
            report.iterations.min(u32::from(u16::MAX)) as u16,
            cost,
        ))
    }

    /// Puts the superposition predictor's start for a frame at tool inputs `tool` into each
    /// direction's x and returns [`Start::Previous`] to solve from it; without held columns
    /// returns [`Start::Predicted`] (the extrapolation) and changes nothing. The previous
    /// frame's solution is the base where there is one, else zero at tool inputs zero.
    fn superpose_start(&mut self, tool: &[[f32; 3]], n: usize) -> Result<Start, ErrorCode> {
        let (tools, started) = self.live.parts().map_err(live)?;
        let Some(columns) = started.columns.clone() else {
            return Ok(Start::Predicted);
        };
        let base = started
            .base
            .filter(|_| self.solution.iter().all(Option::is_some));
        let then = base.unwrap_or([[0.0; 3]; MAX_TOOL_NODES]);
        let g = self
            .store
            .responses
            .get(..tools.len() * n)
            .ok_or(ErrorCode::ChunkTooLong)?;
        for d in 0..MAX_DIRECTIONS {
            let (coeffs, own) = started.superpose_terms(d, tools, tool, &then);
            let e_x = base.and(self.solution[d]);
            let x = self.store.directions[d]
                .x
                .get_mut(..n)
                .ok_or(ErrorCode::ChunkTooLong)?;
            let Some(e) = superpose(x, e_x, g, &columns, &coeffs[..tools.len()], &own) else {
                // x may hold a mix of predictions: no solution is left.
                self.solution = [None; MAX_DIRECTIONS];
                return Err(live(LiveError::NotFinite));
            };
            self.solution[d] = Some(e);
        }
        Ok(Start::Previous)
    }

    /// A force query between a displacement tool's frames, from the local linear model.
    pub(super) fn live_force(&mut self, tool: &[[f32; 3]]) -> Result<Response, ErrorCode> {
        let (force, cost) = self.live_query(tool, ToolKind::Displacement)?;
        let (cycles, stall_cycles) = live_counts(cost);
        Ok(Response::LiveForce(ForceReport {
            force,
            cycles,
            stall_cycles,
        }))
    }

    /// A displacement query between a force tool's frames, from the compliance model.
    pub(super) fn live_load_query(&mut self, load: &[[f32; 3]]) -> Result<Response, ErrorCode> {
        let (displacement, cost) = self.live_query(load, ToolKind::Force)?;
        let (cycles, stall_cycles) = live_counts(cost);
        Ok(Response::LiveMotionQuery(MotionQuery {
            displacement,
            cycles,
            stall_cycles,
        }))
    }

    /// The local model's answer at `tool` and hart 0's counts for it.
    fn live_query(
        &mut self,
        tool: &[[f32; 3]],
        kind: ToolKind,
    ) -> Result<([f32; 3], PhaseCounters), ErrorCode> {
        let t0 = self.exec.now();
        self.check_tool(tool, kind)?;
        let (_, started) = self.live.parts().map_err(live)?;
        let answer = started.model_answer(tool).map_err(live)?;
        Ok((answer.map(|v| v as f32), self.exec.now().since(t0)))
    }

    /// A chunk of the last frame's field, quantised (see [`FieldChunk`]): the selection's
    /// nodes `offset`, `offset + stride`, …, checked against the resident matrix first.
    pub(super) fn read_field(
        &mut self,
        offset: u32,
        stride: u16,
        surface: Option<[u16; 3]>,
    ) -> Result<Response, ErrorCode> {
        let t0 = self.exec.now();
        let shape = self.resident()?;
        let n = to_usize(shape.n);
        let selection = FieldSelection::new(shape.n, stride, surface).map_err(live)?;
        if offset >= selection.len() {
            return Err(live(LiveError::FieldOffset {
                offset,
                selected: selection.len(),
            }));
        }
        let mut exponents = [0i32; MAX_DIRECTIONS];
        for (d, e) in exponents.iter_mut().enumerate() {
            *e = self.solution[d].ok_or(out_of_order(SessionStep::NoSolution))?;
        }
        let (_, started) = self.live.parts().map_err(live)?;
        let dirs = &self.store.directions;
        let solutions: [(&[i32], i32); MAX_DIRECTIONS] =
            core::array::from_fn(|d| (dirs[d].x.get(..n).unwrap_or(&[]), exponents[d]));
        let exponent = *started
            .field_exponent
            .get_or_insert_with(|| field_exponent(&solutions));
        let values = pack_field(&solutions, selection.chunk(offset), exponent);
        let (cycles, stall_cycles) = live_counts(self.exec.now().since(t0));
        Ok(Response::Field(FieldChunk {
            offset,
            exponent,
            cycles,
            stall_cycles,
            values,
        }))
    }
}

/// Keeps the solved column `z` (exponent `e_z`) of tool node `j` in `responses` if every
/// tool node's column fits there; the first column decides, the others follow it.
fn hold_column(
    started: &mut Started,
    responses: &mut [i32],
    tools: usize,
    j: usize,
    z: &[i32],
    e_z: i32,
) {
    let n = z.len();
    if j == 0 {
        let room = responses.len() / n.max(1);
        started.columns = (tools <= room).then(heapless::Vec::new);
    }
    let Some(columns) = started.columns.as_mut() else {
        return;
    };
    if let Some(dst) = responses.get_mut(j * n..(j + 1) * n) {
        dst.copy_from_slice(z);
        let _ = columns.push(Column::of(z, e_z));
    }
}

/// A frame's cycles and instructions on the critical path, from hart 0's counts over the frame
/// (`elapsed`). With one MVU those counts are the frame's. With several, QEMU `-icount` gives
/// every hart one machine-wide counter, so hart 0's count over the solve is all harts' work
/// added up: the solve's share is replaced by its measured critical path
/// (`SolveReport::whole_solve`: every parallel phase's slowest hart plus hart 0's serial work),
/// and hart 0's own work around the solve (right-hand sides, prediction, reaction force) is kept
/// as it is.
fn frame_cost(elapsed: PhaseCounters, report: &SolveReport) -> PhaseCounters {
    let (on_hart0, critical) = solve_cost(report);
    elapsed.saturating_sub(on_hart0).saturating_add(critical)
}

/// A solve's share of hart 0's counts and its critical path; the same with one MVU.
fn solve_cost(report: &SolveReport) -> (PhaseCounters, PhaseCounters) {
    let on_hart0 = report.mvu.saturating_add(report.svu);
    if report.mvus <= 1 {
        return (on_hart0, on_hart0);
    }
    (on_hart0, report.whole_solve.critical())
}

/// A live report's `cycles` and `stall_cycles` (cycles − instructions), each clamped to 32 bits.
fn live_counts(cost: PhaseCounters) -> (u32, u32) {
    let clamp = |v: u64| v.min(u64::from(u32::MAX)) as u32;
    (clamp(cost.cycles), clamp(cost.stall_cycles()))
}
