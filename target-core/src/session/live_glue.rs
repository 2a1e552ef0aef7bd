//! The session's live-loop requests (protocol version 8, [`deform_shared::live`]): the tool
//! set, the local force model, full frames, force queries and the quantised field. The
//! arithmetic is in [`crate::live`]; this is where it meets the session's vectors and solves.

use deform_shared::live::{
    FieldChunk, FieldSelection, ForceReport, FrameReport, LiveError, LiveParams, ModelReport,
    ToolRow,
};

use super::*;
use crate::live::{field_exponent, pack_field, tool_mantissas};
use deform_shared::protocol::SolveReport;

/// The Schur columns' tolerance: the fixed-point CG's floor, which the host's refinement
/// also uses.
const MODEL_TOLERANCE: f64 = 1e-7;

fn live(e: LiveError) -> ErrorCode {
    ErrorCode::Live(e)
}

impl<E: Executor> Session<'_, E> {
    pub(super) fn live_tool(&mut self, row: ToolRow) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        self.live.add_tool(row, shape.n).map_err(live)?;
        Ok(Response::Ack)
    }

    /// Starts the live session: one fused CG solve per three tool nodes gives the Schur
    /// complement's column sums. The right-hand sides, solutions and predictions are spent.
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
        };
        let result = (|| {
            for first in (0..tools).step_by(MAX_DIRECTIONS) {
                let group = (tools - first).min(MAX_DIRECTIONS);
                for g in 0..group {
                    let (tools, started) = self.live.parts().map_err(live)?;
                    let b = self.store.directions[g]
                        .b
                        .get_mut(..n)
                        .ok_or(ErrorCode::ChunkTooLong)?;
                    started.schur_rhs(tools, first + g, b);
                    self.rhs[g] = VectorState::Complete { exponent: -f };
                }
                let solved = self.solve(&SolveParams {
                    max_iterations: shape.n.saturating_mul(10),
                    tolerance: MODEL_TOLERANCE,
                    start: Start::Zero,
                    directions: group as u8,
                    cycle_budget: 0,
                })?;
                if let Response::Solved(r) = solved {
                    report.solves += 1;
                    report.iterations += r.iterations;
                    report.converged &= r.converged;
                }
                for g in 0..group {
                    let e_z = self.solution[g].unwrap_or(0);
                    let (tools, started) = self.live.parts().map_err(live)?;
                    let z = self.store.directions[g].x.get(..n).unwrap_or(&[]);
                    started.set_schur(tools, first + g, z, e_z, f);
                }
            }
            Ok(())
        })();
        // The vectors now hold the model's columns, not anything the host sent.
        self.rhs = [VectorState::Empty; MAX_DIRECTIONS];
        self.solution = [None; MAX_DIRECTIONS];
        self.kept = [None; MAX_DIRECTIONS];
        if let Err(e) = result {
            self.live.clear();
            return Err(e);
        }
        report.cycles = self.exec.now().cycles.wrapping_sub(t0.cycles);
        Ok(Response::LiveReady(report))
    }

    /// Checks a frame's or query's tool displacements against the tool set.
    fn check_tool(&mut self, tool: &[[f32; 3]]) -> Result<(), ErrorCode> {
        let (tools, _) = self.live.parts().map_err(live)?;
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

    /// A full frame: right-hand sides from the tool displacements, a fused predicted solve
    /// within the budget, the reaction force, and the local model re-anchored.
    pub(super) fn live_frame(&mut self, tool: &[[f32; 3]]) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        let (n, f) = (to_usize(shape.n), i32::from(shape.frac_bits));
        let t0 = self.exec.now();
        self.check_tool(tool)?;
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
                let (u, e_u) = tool_mantissas(tool, d).map_err(live)?;
                let e = started.patch_rhs(d, tools, b, e_b, &u, e_u, f);
                self.rhs[d] = VectorState::Complete { exponent: e };
            }
            started.params
        };
        let Response::Solved(report) = self.solve(&SolveParams {
            max_iterations: params.max_iterations,
            tolerance: f64::from(params.tolerance),
            start: Start::Predicted,
            directions: MAX_DIRECTIONS as u8,
            cycle_budget: params.cycle_budget,
        })?
        else {
            return Err(out_of_order(SessionStep::NoSolution));
        };
        let (tools, started) = self.live.parts().map_err(live)?;
        let mut force = [0f64; 3];
        for (d, out) in force.iter_mut().enumerate() {
            let (u, e_u) = tool_mantissas(tool, d).map_err(live)?;
            let x = self.store.directions[d].x.get(..n).unwrap_or(&[]);
            let e_x = self.solution[d].unwrap_or(0);
            *out = f64::from(params.scale[d]) * started.reaction(tools, x, e_x, &u, e_u, f);
        }
        started.anchor(force, tool);
        let cycles = frame_cycles(self.exec.now().cycles.wrapping_sub(t0.cycles), &report);
        Ok(Response::LiveFrame(FrameReport {
            force: force.map(|v| v as f32),
            residual: report.residual as f32,
            iterations: report.iterations.min(u32::from(u16::MAX)) as u16,
            cycles: cycles.min(u64::from(u32::MAX)) as u32,
        }))
    }

    /// A force query between frames, from the local linear model.
    pub(super) fn live_force(&mut self, tool: &[[f32; 3]]) -> Result<Response, ErrorCode> {
        let t0 = self.exec.now();
        self.check_tool(tool)?;
        let (_, started) = self.live.parts().map_err(live)?;
        let force = started.model_force(tool).map_err(live)?;
        let cycles = self.exec.now().cycles.wrapping_sub(t0.cycles);
        Ok(Response::LiveForce(ForceReport {
            force: force.map(|v| v as f32),
            cycles: cycles.min(u64::from(u32::MAX)) as u32,
        }))
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
        let cycles = self.exec.now().cycles.wrapping_sub(t0.cycles);
        Ok(Response::Field(FieldChunk {
            offset,
            exponent,
            cycles: cycles.min(u64::from(u32::MAX)) as u32,
            values,
        }))
    }
}

/// A frame's cycles on the critical path, from hart 0's cycle count over the frame (`elapsed`).
/// With one MVU that count is the frame's time. With several, QEMU `-icount` gives every hart
/// one machine-wide counter, so hart 0's count over the solve is all harts' work added up: the
/// solve's share is replaced by its measured critical path (`SolveReport::whole_solve`: every
/// parallel phase's slowest hart plus hart 0's serial work), and hart 0's own work around the
/// solve (right-hand sides, prediction, reaction force) is kept as it is.
fn frame_cycles(elapsed: u64, report: &SolveReport) -> u64 {
    if report.mvus <= 1 {
        return elapsed;
    }
    let on_hart0 = report.mvu.cycles.saturating_add(report.svu.cycles);
    let critical = report
        .whole_solve
        .mvu_critical
        .saturating_add(report.whole_solve.svu_critical);
    elapsed.saturating_sub(on_hart0).saturating_add(critical)
}
