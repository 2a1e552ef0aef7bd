//! The session's live-loop requests (protocol versions 8 and 9, [`deform_shared::live`]): the
//! tool set (displacement rows or force nodes), the local model (Schur sums or compliance),
//! full frames, queries between them and the quantised field. The
//! arithmetic is in [`crate::live`]; this is where it meets the session's vectors and solves.

use deform_shared::live::{
    FieldChunk, FieldSelection, ForceReport, FrameReport, LiveError, LiveParams, ModelReport,
    MotionQuery, MotionReport, ToolRow,
};

use super::*;
use crate::cg::EXACT_PASS_ERROR;
use crate::exec::{share, slowest, SharedSlice};
use crate::live::{field_exponent, pack_field, Estimate, Started, ToolKind};
use crate::predict::scale;
use crate::superpose::{
    apply_share, bound_from_or, ceil_sqrt, sqrt_up, verdict, Column, ErrorBound, ShareSums, Terms,
    Verdict, EXACT_EVERY,
};
use crate::svu::magnitude_bits;
use deform_shared::live::MAX_TOOL_NODES;
use deform_shared::protocol::{PhaseCounters, SolveReport, MAX_HARTS};
use deform_shared::qformat::ldexp;

/// The Schur columns' tolerance: the fixed-point CG's floor, which the host's refinement
/// also uses.
const MODEL_TOLERANCE: f64 = deform_shared::qformat::FIXED_POINT_FLOOR;

fn live(e: LiveError) -> ErrorCode {
    ErrorCode::Live(e)
}

impl<E: Executor> Session<'_, E> {
    pub(super) fn live_tool(&mut self, row: ToolRow) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        self.dynamic.clear();
        self.live.add_tool(row, shape.n).map_err(live)?;
        Ok(Response::Ack)
    }

    /// A force tool at `nodes` (version 9).
    pub(super) fn live_force_tool(&mut self, nodes: &[u32]) -> Result<Response, ErrorCode> {
        let shape = self.loaded()?;
        self.dynamic.clear();
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
        // Hart 0's counts over the solves and their critical paths (see [`solve_cost`]).
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
                // The held columns' own residuals c_j − K·G_j, by an exact pass (no iteration).
                if self.live.started().is_some_and(|s| s.columns.is_some()) {
                    let which: heapless::Vec<usize, MAX_DIRECTIONS> = (0..group).collect();
                    let (r, outcomes) = self.solve_directions(
                        &SolveParams {
                            max_iterations: 0,
                            tolerance: 0.0,
                            start: Start::Previous,
                            directions: group as u8,
                            cycle_budget: 0,
                        },
                        &which,
                        [None; MAX_DIRECTIONS],
                        false,
                    )?;
                    let (on_hart0, critical) = solve_cost(&r);
                    counted = counted.saturating_add(on_hart0);
                    path = path.saturating_add(critical);
                    for (g, outcome) in outcomes.iter().enumerate().take(group) {
                        let (tools, started) = self.live.parts().map_err(live)?;
                        let rho = self.store.directions[g].r.get(..n).unwrap_or(&[]);
                        let held = &mut self.store.residuals;
                        hold_residual(started, held, tools.len(), first + g, rho, outcome);
                    }
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

    /// A full frame: right-hand sides from the tool inputs, the superposed start and its
    /// residual estimate, a solve of the directions that need one (none where every estimate
    /// is accepted), the answer (force or motion), and the local model re-anchored. Returns
    /// the answer, the residual, the iterations and the frame's cost (hart 0's counts over
    /// the frame, the solve's share replaced by its critical path: [`solve_cost`]).
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
        let mut inputs: [(heapless::Vec<i32, MAX_TOOL_NODES>, i32); MAX_DIRECTIONS] =
            Default::default();
        let params = {
            let (tools, started) = self.live.parts().map_err(live)?;
            for (d, e_b) in exponents.into_iter().enumerate() {
                let b = self.store.directions[d]
                    .b
                    .get_mut(..n)
                    .ok_or(ErrorCode::ChunkTooLong)?;
                started.take_snapshot(d, tools, b, e_b);
                inputs[d] = started.tool_input(d, tool).map_err(live)?;
                let input = (&inputs[d].0[..], inputs[d].1);
                let e = started.patch(d, tools, b, e_b, input, f);
                self.rhs[d] = VectorState::Complete { exponent: e };
            }
            started.params
        };
        let solve = SolveParams {
            max_iterations: params.max_iterations,
            tolerance: f64::from(params.tolerance),
            start: Start::Predicted,
            directions: MAX_DIRECTIONS as u8,
            cycle_budget: params.cycle_budget,
        };
        // The frame's superposed start (or, without held columns, the extrapolation).
        let report = match self.superpose_frame(tool, n, f, &inputs)? {
            Some(frame) => self.finish_superposed(frame, &solve, n)?,
            None => match self.solve(&solve)? {
                Response::Solved(report) => FrameSolve::of(&report),
                _ => return Err(out_of_order(SessionStep::NoSolution)),
            },
        };
        let (tools, started) = self.live.parts().map_err(live)?;
        let mut answer = [0f64; 3];
        for (d, out) in answer.iter_mut().enumerate() {
            let x = self.store.directions[d].x.get(..n).unwrap_or(&[]);
            let e_x = self.solution[d].unwrap_or(0);
            let input = (&inputs[d].0[..], inputs[d].1);
            *out = started.answer(d, tools, x, e_x, input, f).map_err(live)?;
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
        let cost = self
            .exec
            .now()
            .since(t0)
            .saturating_sub(report.on_hart0)
            .saturating_add(report.critical);
        Ok((
            answer.map(|v| v as f32),
            report.residual as f32,
            report.iterations.min(u32::from(u16::MAX)) as u16,
            cost,
        ))
    }

    /// The superposed start of a frame at tool inputs `tool` in every direction's x, and
    /// where the columns' residuals are held the estimate of r₀ in r with its verdict
    /// ([`crate::superpose`]); one parallel pass over the directions the tool moved. `None`
    /// (nothing changed) where the columns are not held: the frame falls back to the
    /// extrapolation. The previous frame's solution is the base where there is one, else zero
    /// at tool inputs zero.
    fn superpose_frame(
        &mut self,
        tool: &[[f32; 3]],
        n: usize,
        f: i32,
        inputs: &[(heapless::Vec<i32, MAX_TOOL_NODES>, i32); MAX_DIRECTIONS],
    ) -> Result<Option<SuperposedFrame>, ErrorCode> {
        let plan = self.plan.ok_or(out_of_order(SessionStep::NoMatrix))?;
        let (tools, started) = self.live.parts().map_err(live)?;
        let Some(columns) = started.columns.as_ref() else {
            return Ok(None);
        };
        let base = started
            .base
            .filter(|_| self.solution.iter().all(Option::is_some));
        let then = base.unwrap_or([[0.0; 3]; MAX_TOOL_NODES]);
        let mut frame = SuperposedFrame::default();
        for (d, input) in inputs.iter().enumerate() {
            let (coeffs, own) = started.superpose_terms(d, tools, tool, &then);
            let coeffs = &coeffs[..tools.len()];
            let estimate = base.and(started.estimates[d]);
            let x_bound =
                |x: &[i32]| bound_from_or(x.iter().fold(0, |o, &v| o | magnitude_bits(v)));
            let prev = base.and(self.solution[d]).map(|e| {
                let x = self.store.directions[d].x.get(..n).unwrap_or(&[]);
                (e, estimate.map_or_else(|| x_bound(x), |s| s.x_bound))
            });
            let Some((xt, own)) = Terms::plan(prev, columns, coeffs, &own) else {
                // x may hold a mix of predictions: no solution is left.
                self.solution = [None; MAX_DIRECTIONS];
                return Err(live(LiveError::NotFinite));
            };
            let rt = match (estimate, started.residual_columns.as_ref()) {
                (Some(est), Some(res)) => {
                    let res: heapless::Vec<Column, MAX_TOOL_NODES> =
                        res.iter().map(|(c, _)| *c).collect();
                    Terms::plan(Some((est.r_exponent, est.r_bound)), &res, coeffs, &[])
                        .map(|(t, _)| t)
                }
                // A fresh start (x from zero): r is zeroed, right where b is zero too.
                _ => prev.is_none().then(Terms::zero),
            };
            frame.directions[d] = DirectionFrame {
                moved: xt.moves() || !own.is_empty(),
                x: xt,
                own,
                r: rt,
                estimate,
                coeffs: core::array::from_fn(|j| coeffs.get(j).copied().unwrap_or(0.0)),
                input_exponent: input.1,
                ..DirectionFrame::default()
            };
        }
        self.superpose_pass(&mut frame, n, plan.mvus)?;
        let (tools, started) = self.live.parts().map_err(live)?;
        let k_inf = ldexp(plan.row_abs_max as f64, -f);
        let weight = match started.kind {
            ToolKind::Displacement => k_inf,
            ToolKind::Force => 1.0,
        };
        let rows = started.patched_rows(tools.len());
        let tol = f64::from(started.params.tolerance);
        for (d, df) in frame.directions.iter_mut().enumerate() {
            if !df.moved {
                continue;
            }
            self.solution[d] = Some(df.x.e);
            let e_b = self.rhs[d].exponent(SessionStep::NoRhs)?;
            df.verdict = Verdict::Exact;
            if df.estimate.is_none() && df.sums.bb == 0 && df.sums.x_or == 0 {
                // b = 0 and x = 0 (a direction no load acts in): r = 0 exactly.
                df.verdict = Verdict::Accept;
                df.error = 0.0;
                continue;
            }
            let (Some(est), Some(rt), Some(res)) =
                (df.estimate, df.r, started.residual_columns.as_ref())
            else {
                continue;
            };
            let columns: f64 = res
                .iter()
                .zip(&df.coeffs)
                .map(|((_, err), a)| a.abs() * err)
                .sum();
            // b: its patched rows rounded now and before (and all of it if rescaled).
            let (b_units, b_rows) = if e_b == est.b_exponent {
                (2.0, rows)
            } else {
                (1.5 + ldexp(1.0, est.b_exponent - e_b), n)
            };
            let inputs = tools.len() as f64
                * 0.5
                * (ldexp(1.0, df.input_exponent) + ldexp(1.0, est.input_exponent));
            let x_units = df.x.rounding_units();
            let error = ErrorBound { total: est.error }.carried(
                n,
                k_inf,
                (x_units, df.x.e),
                (rt.rounding_units(), rt.e),
                (b_units, e_b, b_rows),
                (inputs, weight),
                columns,
            );
            df.error = error.total;
            df.verdict = if est.frames + 1 >= EXACT_EVERY {
                Verdict::Exact
            } else {
                verdict(df.sums.rr, rt.e, df.sums.bb, e_b, tol, error.total)
            };
        }
        Ok(Some(frame))
    }

    /// The superposition (and estimate) of every moved direction on every hart's share, then
    /// the own terms on hart 0; `frame`'s sums and the pass's cycles are filled in.
    // The harts share x and r through `SharedSlice`s, each writing its own share.
    #[allow(unsafe_code)]
    fn superpose_pass(
        &mut self,
        frame: &mut SuperposedFrame,
        n: usize,
        mvus: usize,
    ) -> Result<(), ErrorCode> {
        let harts = mvus.clamp(1, MAX_HARTS);
        let g = self
            .store
            .responses
            .get(..MAX_TOOL_NODES.min(self.store.responses.len() / n.max(1)) * n)
            .ok_or(ErrorCode::ChunkTooLong)?;
        let rho = self
            .store
            .residuals
            .get(..MAX_TOOL_NODES.min(self.store.residuals.len() / n.max(1)) * n)
            .unwrap_or(&[]);
        let mut sums = [[ShareSums::default(); MAX_DIRECTIONS]; MAX_HARTS];
        {
            let dirs = &frame.directions;
            let sums = SharedSlice::new(&mut sums);
            let mut xs: [&mut [i32]; MAX_DIRECTIONS] = Default::default();
            let mut rs: [&mut [i32]; MAX_DIRECTIONS] = Default::default();
            let mut bs: [&[i32]; MAX_DIRECTIONS] = Default::default();
            for (d, v) in self.store.directions.iter_mut().enumerate() {
                xs[d] = v.x.get_mut(..n).ok_or(ErrorCode::ChunkTooLong)?;
                rs[d] = v.r.get_mut(..n).ok_or(ErrorCode::ChunkTooLong)?;
                bs[d] = v.b.get(..n).ok_or(ErrorCode::ChunkTooLong)?;
            }
            let xs = xs.map(SharedSlice::new);
            let rs = rs.map(SharedSlice::new);
            let task = |h: usize| {
                let range = share(n, harts, h);
                for (d, df) in dirs.iter().enumerate().filter(|(_, df)| df.moved) {
                    // SAFETY: each hart writes only its own share of x and r and its own
                    // slot of the sums; the columns and b are only read.
                    unsafe {
                        let out = apply_share(
                            xs[d].slice_mut(range.clone()),
                            rs[d].slice_mut(range.clone()),
                            &bs[d][range.clone()],
                            range.start,
                            n,
                            g,
                            rho,
                            &df.x,
                            df.r.as_ref(),
                        );
                        sums.slice_mut(h..h + 1)[0][d] = out;
                    }
                }
            };
            let t = self.exec.now();
            let counts = self.exec.run_measured(harts, &task);
            frame.on_hart0 = self.exec.now().since(t);
            frame.critical = slowest(&counts[..harts]);
        }
        for (d, df) in frame.directions.iter_mut().enumerate() {
            if !df.moved {
                continue;
            }
            let x = self.store.directions[d].x.get_mut(..n).unwrap_or(&mut []);
            let mut x_or = sums.iter().fold(0, |o, s| o | s[d].x_or);
            for &(node, v) in &df.own {
                if let Some(xi) = x.get_mut(node as usize) {
                    // Within the planned bound: below 2^30 with the rest of x.
                    *xi = xi.wrapping_add(v as i32);
                    x_or |= magnitude_bits(*xi);
                }
            }
            df.sums = ShareSums {
                x_or,
                rr: sums.iter().map(|s| s[d].rr).sum(),
                r_or: sums.iter().fold(0, |o, s| o | s[d].r_or),
                bb: sums.iter().map(|s| s[d].bb).sum(),
            };
        }
        Ok(())
    }

    /// Ends a superposed frame: accepted directions keep their estimate, the others are
    /// solved (from the estimate where it is far above the tolerance, else from an exact
    /// pass). Returns the frame's solve figures and hart 0's cycles outside the solve that the
    /// parallel pass took.
    fn finish_superposed(
        &mut self,
        frame: SuperposedFrame,
        solve: &SolveParams,
        n: usize,
    ) -> Result<FrameSolve, ErrorCode> {
        let mut which: heapless::Vec<usize, MAX_DIRECTIONS> = heapless::Vec::new();
        let mut r_start = [None; MAX_DIRECTIONS];
        let mut residual = 0f64;
        for (d, df) in frame.directions.iter().enumerate() {
            match (df.moved, df.verdict) {
                (false, _) => {}
                (true, Verdict::Accept) => {
                    residual = residual.max(accepted_residual(df, self.rhs[d])?);
                }
                (true, Verdict::Iterate) => {
                    let _ = which.push(d);
                    r_start[d] = df.r.map(|rt| GivenResidual {
                        exponent: rt.e,
                        rr: df.sums.rr,
                        bound: bound_from_or(df.sums.r_or),
                        verify: true,
                        drift: None,
                    });
                }
                (true, Verdict::Exact) => {
                    let _ = which.push(d);
                }
            }
        }
        let mut out = FrameSolve {
            residual,
            iterations: 0,
            on_hart0: frame.on_hart0,
            critical: frame.critical,
        };
        let outcomes = if which.is_empty() {
            [None; MAX_DIRECTIONS]
        } else {
            let params = SolveParams {
                start: Start::Previous,
                directions: which.len() as u8,
                ..*solve
            };
            let (report, outcomes) = self.solve_directions(&params, &which, r_start, true)?;
            let solved = FrameSolve::of(&report);
            out.residual = out.residual.max(solved.residual);
            out.iterations = solved.iterations;
            out.on_hart0 = out.on_hart0.saturating_add(solved.on_hart0);
            out.critical = out.critical.saturating_add(solved.critical);
            outcomes.map(Some)
        };
        let (_, started) = self.live.parts().map_err(live)?;
        for (d, df) in frame.directions.iter().enumerate() {
            let e_b = self.rhs[d].exponent(SessionStep::NoRhs)?;
            let next = match (df.moved, outcomes[d].filter(|_| which.contains(&d))) {
                (false, _) => df.estimate,
                (true, Some(o)) => Some(Estimate {
                    r_exponent: o.r_exponent,
                    r_bound: o.r_bound,
                    x_bound: o.x_bound,
                    error: if o.r_exact {
                        ErrorBound::exact(n, o.r_exponent).total
                    } else {
                        f64::INFINITY
                    },
                    frames: 0,
                    b_exponent: e_b,
                    input_exponent: df.input_exponent,
                }),
                (true, None) => df.r.map(|rt| Estimate {
                    r_exponent: rt.e,
                    r_bound: bound_from_or(df.sums.r_or),
                    x_bound: bound_from_or(df.sums.x_or),
                    error: df.error,
                    frames: df.estimate.map_or(0, |est| est.frames + 1),
                    b_exponent: e_b,
                    input_exponent: df.input_exponent,
                }),
            };
            started.estimates[d] = next;
        }
        Ok(out)
    }
    /// Each direction's residual estimate state after the last frame (tests: which frames
    /// skipped the exact pass).
    #[cfg(test)]
    pub(crate) fn live_estimates(&self) -> [Option<Estimate>; MAX_DIRECTIONS] {
        self.live
            .started()
            .map_or([None; MAX_DIRECTIONS], |s| s.estimates)
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

    /// A chunk of the last frame's field (a live frame's or a dynamic step's), quantised (see
    /// [`FieldChunk`]): the selection's nodes `offset`, `offset + stride`, …, checked against
    /// the resident matrix first.
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
        // A live session's frame, or a dynamic session's step: each fixes its field's
        // exponent at the first chunk.
        let slot = match self.live.parts() {
            Ok((_, started)) => &mut started.field_exponent,
            Err(e) => match self.dynamic.parts() {
                Ok((_, stepping)) => &mut stepping.field_exponent,
                Err(_) => return Err(live(e)),
            },
        };
        let dirs = &self.store.directions;
        let solutions: [(&[i32], i32); MAX_DIRECTIONS] =
            core::array::from_fn(|d| (dirs[d].x.get(..n).unwrap_or(&[]), exponents[d]));
        let exponent = *slot.get_or_insert_with(|| field_exponent(&solutions));
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

/// A frame's solve figures: its residual, iterations, and hart 0's cycles over the solve (and
/// the superposition pass) against their critical path. A frame's cycles are its critical
/// path: with one MVU hart 0's count over the frame is the frame's time; with several, QEMU
/// `-icount` gives every hart one machine-wide counter, so hart 0's count over a parallel
/// phase is all harts' work added up, and is replaced by the phase's measured critical path
/// (`SolveReport::whole_solve` for a solve: every parallel phase's slowest hart plus hart 0's
/// serial work), while hart 0's own work around them (right-hand sides, prediction, reaction
/// force) is kept as it is.
#[derive(Debug, Clone, Copy, Default)]
struct FrameSolve {
    residual: f64,
    iterations: u32,
    on_hart0: PhaseCounters,
    critical: PhaseCounters,
}

impl FrameSolve {
    fn of(report: &SolveReport) -> FrameSolve {
        let (on_hart0, critical) = solve_cost(report);
        FrameSolve {
            residual: report.residual,
            iterations: report.iterations,
            on_hart0,
            critical,
        }
    }
}

/// One direction of a superposed frame: its planned updates, what the pass measured and the
/// verdict on its estimate.
#[derive(Debug, Clone, Default)]
struct DirectionFrame {
    /// The tool moved in this direction (else x, r and b stay as they are).
    moved: bool,
    x: Terms,
    own: heapless::Vec<(u32, i64), MAX_TOOL_NODES>,
    /// The estimate's update of r, where the residual columns and the previous state are held.
    r: Option<Terms>,
    /// The previous frame's state.
    estimate: Option<Estimate>,
    coeffs: [f64; MAX_TOOL_NODES],
    input_exponent: i32,
    sums: ShareSums,
    verdict: Verdict,
    error: f64,
}

#[derive(Debug, Clone, Default)]
struct SuperposedFrame {
    directions: [DirectionFrame; MAX_DIRECTIONS],
    /// Hart 0's counts over the parallel pass, and its critical path.
    on_hart0: PhaseCounters,
    critical: PhaseCounters,
}

/// The residual an accepted direction reports: (‖r̃‖ + its bound)/‖b‖, what it is certified
/// below.
fn accepted_residual(df: &DirectionFrame, b: VectorState) -> Result<f64, ErrorCode> {
    let e_b = b.exponent(SessionStep::NoRhs)?;
    let e_r = df.r.map_or(0, |t| t.e);
    let norm_b = sqrt_up(ldexp(df.sums.bb as f64, 2 * e_b));
    if norm_b == 0.0 {
        return Ok(0.0);
    }
    Ok((sqrt_up(ldexp(df.sums.rr as f64, 2 * e_r)) + df.error) / norm_b)
}

/// Keeps the residual `rho` (exponent `outcome.r_exponent`, formed by an exact pass) of tool
/// node `j`'s column in `residuals` as `i16` mantissas, if every tool node's fits there and
/// its column is held; the first decides, the others follow it. The stored error bound is the
/// pass's and the `i16` rounding's.
fn hold_residual(
    started: &mut Started,
    residuals: &mut [i16],
    tools: usize,
    j: usize,
    rho: &[i32],
    outcome: &Outcome,
) {
    let n = rho.len();
    if j == 0 {
        let room = residuals.len() / n.max(1);
        started.residual_columns = (tools <= room && started.columns.is_some() && outcome.r_exact)
            .then(heapless::Vec::new);
    }
    let (Some(columns), Some(dst)) = (
        started.residual_columns.as_mut(),
        residuals.get_mut(j * n..(j + 1) * n),
    ) else {
        return;
    };
    if !outcome.r_exact {
        started.residual_columns = None;
        return;
    }
    let max = rho.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0);
    // i16 mantissas below 2^15: the shift from r's exponent, rounded to nearest.
    let shift = (32 - max.leading_zeros() as i32 - 15).max(0);
    for (o, &v) in dst.iter_mut().zip(rho) {
        *o = scale(i64::from(v), shift).clamp(-32767, 32767) as i16;
    }
    let exponent = outcome.r_exponent + shift;
    let stored = if shift > 0 { 0.5 } else { 0.0 };
    let error =
        ceil_sqrt(n) * (ldexp(stored, exponent) + ldexp(EXACT_PASS_ERROR, outcome.r_exponent));
    let column = Column {
        exponent,
        max: dst
            .iter()
            .map(|v| u32::from(v.unsigned_abs()))
            .max()
            .unwrap_or(0),
    };
    let _ = columns.push((column, error));
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

/// A solve's share of hart 0's counts and its critical path; the same with one MVU.
pub(super) fn solve_cost(report: &SolveReport) -> (PhaseCounters, PhaseCounters) {
    let on_hart0 = report.mvu.saturating_add(report.svu);
    if report.mvus <= 1 {
        return (on_hart0, on_hart0);
    }
    (on_hart0, report.whole_solve.critical())
}

/// A live report's `cycles` and `stall_cycles` (cycles − instructions), each clamped to 32 bits.
pub(super) fn live_counts(cost: PhaseCounters) -> (u32, u32) {
    let clamp = |v: u64| v.min(u64::from(u32::MAX)) as u32;
    (clamp(cost.cycles), clamp(cost.stall_cycles()))
}
