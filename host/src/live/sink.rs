//! Where a headless session's frames go as they come: `--frames-csv` (one typed row per
//! frame, [`FrameRow`]) and `--out` (the frame's solution as a ParaView series), through
//! [`RunFiles`]. Every engine writes through it, so every output flag works on every
//! target; a write error stops the session at that frame, whatever the engine.

use std::fmt::Display;
use std::path::Path;

use super::engine::Frame;
use super::setup::ToolKind;
use crate::model::Model;
use crate::output::csv::{CsvRow, Maybe, Sci};
use crate::output::node_rows;
use crate::output::series::{Numbering, RunFiles};

/// One frame as `--frames-csv` writes it: t, the tool, the answer and its reference (a force
/// tool's `ux,uy,uz` columns; a displacement tool's `fx,fy,fz`), residual, iterations, cycles,
/// the error against the f64 reference, bytes up and down, and for a dynamic frame its motion.
pub struct FrameRow<'a> {
    pub kind: ToolKind,
    pub frame: &'a Frame,
}

impl CsvRow for FrameRow<'_> {
    fn columns(&self, column: &mut dyn FnMut(&'static str, &dyn Display)) {
        let r = self.frame;
        let (answer, reference) = match self.kind {
            ToolKind::Displacement => (["fx", "fy", "fz"], ["fx_ref", "fy_ref", "fz_ref"]),
            ToolKind::Force => (["ux", "uy", "uz"], ["ux_ref", "uy_ref", "uz_ref"]),
        };
        column("frame", &r.frame);
        column("t", &r.t);
        let u = r.tool.first().copied().unwrap_or([0.0; 3]);
        for (name, v) in ["tool_x", "tool_y", "tool_z"].into_iter().zip(u) {
            column(name, &v);
        }
        for (name, v) in answer.into_iter().zip(r.answer) {
            column(name, &v);
        }
        for (name, v) in reference.into_iter().zip(r.reference) {
            column(name, &v);
        }
        column("residual", &Sci(r.residual));
        column("iterations", &r.iterations);
        column("cycles", &Maybe(r.cycles));
        column("error_vs_converged", &Maybe(r.error_vs_converged.map(Sci)));
        column("bytes_up", &r.bytes.sent);
        column("bytes_down", &r.bytes.received);
        if let Some(m) = r.motion {
            column("max_u", &Sci(r.max_u));
            column("max_v", &Sci(m.max_v));
            column("energy", &Sci(m.energy));
        }
    }
}

/// `--frames-csv` and `--out` of a session.
pub struct FrameSink<'m> {
    model: &'m Model,
    kind: ToolKind,
    files: RunFiles,
}

impl<'m> FrameSink<'m> {
    /// Creates the files (checked beforehand, see [`crate::output::paths`]); `dynamic` frames
    /// have the motion columns.
    pub fn create(
        model: &'m Model,
        kind: ToolKind,
        dynamic: bool,
        csv: Option<&Path>,
        out: Option<&Path>,
    ) -> anyhow::Result<Self> {
        let template = Frame {
            motion: dynamic.then(Default::default),
            ..Frame::default()
        };
        let row = FrameRow {
            kind,
            frame: &template,
        };
        Ok(Self {
            model,
            kind,
            files: RunFiles::create(csv, &row, out, Numbering::FRAMES)?,
        })
    }

    /// Writes `frame` (and `u`, its solution, to the series where the engine holds one).
    pub fn write(&mut self, frame: &Frame, u: Option<&[Vec<f64>; 3]>) -> anyhow::Result<()> {
        let row = FrameRow {
            kind: self.kind,
            frame,
        };
        let model = self.model;
        self.files.write(&row, frame.frame, frame.t, || {
            u.map(|u| node_rows(model, u))
        })
    }

    /// Gives the files their real names and writes the series' collection; the lines to print.
    pub fn finish(self) -> anyhow::Result<Vec<String>> {
        self.files.finish()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::live::engine::Motion;

    /// The quasi-static and dynamic tables keep their columns (the dynamic one once had 9
    /// header names for 11 values).
    #[test]
    fn the_frame_tables_name_every_column() {
        let frame = Frame {
            frame: 2,
            t: 0.5,
            tool: vec![[0.0, 0.0, -1.0]],
            answer: [0.25, 0.0, 1.0],
            reference: [0.25, 0.0, 1.0],
            residual: 1e-5,
            iterations: 3,
            cycles: Some(1234),
            error_vs_converged: Some(2e-7),
            ..Frame::default()
        };
        let row = FrameRow {
            kind: ToolKind::Displacement,
            frame: &frame,
        };
        assert_eq!(
            row.header(),
            "frame,t,tool_x,tool_y,tool_z,fx,fy,fz,fx_ref,fy_ref,fz_ref,residual,iterations,\
             cycles,error_vs_converged,bytes_up,bytes_down"
        );
        assert_eq!(
            row.line(),
            "2,0.5,0,0,-1,0.25,0,1,0.25,0,1,1e-5,3,1234,2e-7,0,0"
        );
        let force = FrameRow {
            kind: ToolKind::Force,
            frame: &frame,
        };
        assert!(force.header().contains(",ux,uy,uz,ux_ref,uy_ref,uz_ref,"));
        let dynamic = Frame {
            motion: Some(Motion {
                max_v: 0.5,
                energy: 2.0,
            }),
            cycles: None,
            error_vs_converged: None,
            max_u: 1.0,
            ..frame
        };
        let row = FrameRow {
            kind: ToolKind::Displacement,
            frame: &dynamic,
        };
        assert!(row
            .header()
            .ends_with(",bytes_up,bytes_down,max_u,max_v,energy"));
        assert_eq!(
            row.header().split(',').count(),
            row.line().split(',').count()
        );
        assert!(
            row.line().contains(",3,,,0,0,1e0,5e-1,2e0"),
            "{}",
            row.line()
        );
    }
}
