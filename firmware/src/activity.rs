//! What the firmware logs (defmt, see [`crate::logger`]) about the requests it serves.
//!
//! Milestones only: the per-chunk requests (`Words`, `VectorData`, `UpdateValues`,
//! `ReadSolution`, `ReadVector`) log nothing, so a large upload puts no log bytes on the wire. Levels:
//!
//! - `info`: boot, handshakes, a matrix accepted, each solve's outcome and counters;
//! - `warn`: every request refused, with the error code;
//! - `debug`: the parameters of each upload and solve;
//! - `trace`: every milestone request as it arrives.

use deform_shared::protocol::{ErrorCode, Request, Response, Start};

/// Hands `request` to `serve` (the session) and logs what it asked and what came of it.
pub fn logged(request: Request, serve: impl FnOnce(Request) -> Response) -> Response {
    log_request(&request);
    let was_end_matrix = matches!(request, Request::EndMatrix { .. });
    let response = serve(request);
    log_response(&response, was_end_matrix);
    response
}

fn log_request(request: &Request) {
    match request {
        Request::Hello { protocol_version } => {
            defmt::trace!(
                "Hello from a host speaking protocol {=u16}",
                protocol_version
            )
        }
        Request::BeginMatrix {
            n,
            frac_bits,
            tiles,
            words,
        } => defmt::debug!(
            "matrix upload: n = {=u32}, {=u32} tiles, {=u32} words, Q{=u8}",
            n,
            tiles,
            words,
            frac_bits
        ),
        Request::EndMatrix { crc32 } => {
            defmt::trace!("EndMatrix, host CRC {=u32:#010x}", crc32)
        }
        Request::BeginVector { len, exponent, .. } => {
            defmt::debug!(
                "vector upload: {=u32} entries, exponent {=i32}",
                len,
                exponent
            )
        }
        Request::Solve(params) => defmt::debug!(
            "solve: at most {=u32} iterations, tolerance {=f64}, start {=str}",
            params.max_iterations,
            params.tolerance,
            match params.start {
                Start::Zero => "zero",
                Start::Previous => "previous",
                Start::Uploaded => "uploaded",
                Start::Predicted => "predicted",
            }
        ),
        Request::BeginUpdate { words, frac_bits } => {
            defmt::debug!("values-only update: {=u32} words, Q{=u8}", words, frac_bits)
        }
        Request::EndUpdate { crc32 } => {
            defmt::trace!("EndUpdate, host CRC {=u32:#010x}", crc32)
        }
        Request::LiveStart(params) => defmt::debug!(
            "live session: tolerance {=f32}, at most {=u32} iterations, cycle budget {=u64}",
            params.tolerance,
            params.max_iterations,
            params.cycle_budget
        ),
        Request::BeginStiffness { frac_bits } => {
            defmt::debug!("stiffness copy: K's values in Q{=u8}", frac_bits)
        }
        Request::DynamicStart(params) => defmt::debug!(
            "dynamic session: h = {=f32} s, mass {=f32} kg, tolerance {=f32}",
            params.h,
            params.mass,
            params.tolerance
        ),
        // Frames are the hot path: a log line would ride down the line with every answer.
        Request::LiveForceTool { nodes } => {
            defmt::debug!("force tool at {=usize} node(s)", nodes.len())
        }
        Request::LiveTool(_)
        | Request::DynamicTool(_)
        | Request::DynamicFrame { .. }
        | Request::LiveLoad { .. }
        | Request::LiveLoadQuery { .. }
        | Request::LiveFrame { .. }
        | Request::LiveForce { .. }
        | Request::ReadField { .. }
        | Request::Tile(_)
        | Request::Words { .. }
        | Request::VectorData { .. }
        | Request::ReadSolution { .. }
        | Request::ReadVector { .. }
        | Request::UpdateValues { .. } => {}
    }
}

/// `was_end_matrix` if the request was `EndMatrix` (it has been moved into the session by now).
fn log_response(response: &Response, was_end_matrix: bool) {
    match response {
        Response::Hello(info) => defmt::info!(
            "host connected: protocol {=u16}, firmware {=str}",
            info.protocol_version,
            info.firmware_version.as_str()
        ),
        Response::Ack if was_end_matrix => defmt::info!("matrix accepted and resident"),
        Response::Solved(report) => defmt::info!(
            "solved in {=u32} iterations (converged: {=bool}), residual {=f64}; MVU {=u64} cycles / {=u64} instructions, SVU {=u64} cycles / {=u64} instructions (hart 0)",
            report.iterations,
            report.converged,
            report.residual,
            report.mvu.cycles,
            report.mvu.instructions,
            report.svu.cycles,
            report.svu.instructions
        ),
        Response::Error(code) => defmt::warn!("refused: {}", defmt::Debug2Format(code)),
        Response::LiveReady(model) => defmt::info!(
            "live session ready: local force model from {=u8} solve(s), {=u32} iterations, {=u64} cycles, {=u64} stall cycles",
            model.solves,
            model.iterations,
            model.cycles,
            model.stall_cycles
        ),
        Response::Ack
        | Response::Solution { .. }
        | Response::Log { .. }
        | Response::LiveFrame(_)
        | Response::LiveForce(_)
        | Response::LiveMotion(_)
        | Response::LiveMotionQuery(_)
        | Response::Field(_) => {}
    }
}

/// A frame that could not be read as a request: line noise, or the host's flushing delimiter
/// cutting a partial frame short. Common and harmless at a handshake, hence only `debug`.
pub fn unreadable(code: &ErrorCode) {
    defmt::debug!("unreadable frame: {}", defmt::Debug2Format(code));
}
