//! Target-resident dynamic frames (protocol version 12, [`deform_shared::dynamics`]): the host
//! half. Once per session the host uploads S = M + h·C + h²·K (scaled up by a power of two so
//! that its entries use all 21 bits of the value field), K's values into the target's copy of
//! S's words, and each tool node's rows of S and K; then every frame carries the tool's
//! displacements up (at most 64 bytes) and the tool's force down. The target keeps u and v and
//! forms each step's right-hand side itself; the host's f64 stepper stays as the check
//! ([`crate::live::dynamic`]).
//!
//! It applies where the target's step is the host's: backward Euler, one S for x, y and z
//! (isotropic tissue), a uniform nodal mass and no external loads (the tool drives the
//! tissue). Elsewhere the frames fall back to the host-formed right-hand side.

use deform_shared::dynamics::{DynamicParams, DynamicTool};
use deform_shared::live::{Coupling, FrameReport, ToolRow, MAX_TOOL_NODES, MAX_TOOL_ROW};
use deform_shared::matrix::words_crc;
use deform_shared::protocol::{Request, Response};
use deform_shared::qformat::{quantize, QFormatError, MAX_FRAC_BITS};
use deform_shared::word::{Word, VALUE_MASK};

use super::params::Scheme;
use super::step::StepMatrices;
use super::system::DynamicSystem;
use crate::encode::{encode_with, EncodeError, EncodeOptions, EncodedMatrix};
use crate::link::{LinkError, Port, Target};
use crate::model::{Axis, Csr};

/// Why a dynamic session's frames cannot be formed on the target.
#[derive(Debug, thiserror::Error)]
pub enum ResidentError {
    #[error("the target forms backward-Euler steps only (the scheme is {0})")]
    Scheme(Scheme),
    #[error("S differs between the directions (anisotropic tissue): the target holds one")]
    Anisotropic,
    #[error("the nodal masses differ: the target takes one uniform mass")]
    NonUniformMass,
    #[error("{0} tool nodes; a dynamic session drives 1 to {MAX_TOOL_NODES}")]
    ToolCount(usize),
    #[error("tool node {node} couples to {count} nodes; a tool row holds {MAX_TOOL_ROW}")]
    RowTooLong { node: usize, count: usize },
    #[error("S or K does not fit the value field: {0}")]
    Quantize(#[from] QFormatError),
    #[error("encoding S: {0}")]
    Encode(#[from] EncodeError),
}

/// What a session uploads once.
#[derive(Debug, Clone)]
pub struct ResidentSetup {
    /// S·2^−s_scale, encoded.
    pub matrix: EncodedMatrix,
    /// K·2^−k_scale's raw values in the order of `matrix`'s words, and their Q-format.
    pub stiffness: Vec<i32>,
    pub stiffness_frac_bits: u8,
    pub tools: Vec<DynamicTool>,
    pub params: DynamicParams,
}

/// The largest k with max·2^k < 1: the power of two that makes a matrix's entries use all the
/// bits of the value field at its most fractional bits.
fn scale_up(max: f64) -> i32 {
    if !(max > 0.0 && max.is_finite()) {
        return 0;
    }
    let mut k = -max.log2().floor() as i32 - 1;
    while max * 2f64.powi(k + 1) < 1.0 {
        k += 1;
    }
    while max * 2f64.powi(k) >= 1.0 {
        k -= 1;
    }
    k
}

impl ResidentSetup {
    /// The set-up for `system` stepped by `matrices` with the tool at `tools` (node indices,
    /// prescribed), each step solved to `tolerance` within `max_iterations` and
    /// `cycle_budget` (0: none).
    pub fn new(
        system: &DynamicSystem,
        matrices: &StepMatrices,
        tools: &[usize],
        layout: &EncodeOptions,
        tolerance: f64,
        max_iterations: u32,
        cycle_budget: u64,
    ) -> Result<Self, ResidentError> {
        let mass = supported_mass(system, matrices, tools)?;
        let axis = Axis::X;
        let s = matrices.matrix(axis);
        let a = scale_up(s.max_abs());
        let k_full = system.stiffness(axis);
        let c = scale_up(k_full.max_abs());
        let k_frac = MAX_FRAC_BITS;
        let k_at = |i: usize, j: usize| entry(k_full, i, j) * 2f64.powi(c);
        let (matrix, stiffness) = encode_s_and_k(&s.scaled(2f64.powi(a)), &k_at, k_frac, layout)?;
        let rows = ToolRows {
            constrained: system.constrained(),
            tools,
        };
        let tools = tools
            .iter()
            .map(|&t| {
                let s = rows.row(matrices.free(axis), a, matrix.frac_bits, t)?;
                let k = rows.row(k_full, c, k_frac, t)?;
                Ok(DynamicTool {
                    k: on_columns_of(k, &s),
                    s,
                })
            })
            .collect::<Result<Vec<_>, ResidentError>>()?;
        Ok(ResidentSetup {
            matrix,
            stiffness,
            stiffness_frac_bits: k_frac,
            tools,
            params: DynamicParams {
                h: matrices.h as f32,
                mass: mass as f32,
                s_scale: (-a).clamp(i32::from(i8::MIN), i32::from(i8::MAX)) as i8,
                k_scale: (-c).clamp(i32::from(i8::MIN), i32::from(i8::MAX)) as i8,
                tolerance: tolerance as f32,
                max_iterations,
                cycle_budget,
            },
        })
    }

    /// Uploads S, K's values, the tools, and starts the session at rest.
    pub fn start<P: Port>(&self, target: &mut Target<P>) -> Result<(), LinkError> {
        target.upload_matrix(&self.matrix)?;
        let chunk = target.link_mut().chunk_size();
        let begin = Request::BeginStiffness {
            frac_bits: self.stiffness_frac_bits,
        };
        let values = chunk
            .ranges(self.stiffness.len())
            .map(|range| Request::UpdateValues {
                offset: range.start as u32,
                values: self.stiffness[range].iter().copied().collect(),
            });
        let words: Vec<u32> = self
            .matrix
            .words
            .iter()
            .zip(&self.stiffness)
            .map(|(&w, &v)| (w & !VALUE_MASK) | (v as u32 & VALUE_MASK))
            .collect();
        let end = Request::EndUpdate {
            crc32: words_crc(&words),
        };
        let tools = self.tools.iter().cloned().map(Request::DynamicTool);
        let start = Request::DynamicStart(self.params);
        let requests = std::iter::once(begin)
            .chain(values)
            .chain([end])
            .chain(tools)
            .chain([start]);
        target
            .link_mut()
            .run(requests, |request, reply| match reply {
                Response::Ack => Ok(()),
                other => Err(LinkError::Protocol {
                    request: request.name(),
                    expected: "Ack",
                    got: format!("{other:?}"),
                }),
            })
    }

    /// One step with the tool at `tool` at its end: the target's report (force, residual,
    /// iterations, cycles).
    pub fn frame<P: Port>(
        target: &mut Target<P>,
        tool: &[[f64; 3]],
    ) -> Result<FrameReport, LinkError> {
        let request = Request::DynamicFrame {
            tool: tool.iter().map(|u| u.map(|v| v as f32)).collect(),
        };
        let timeout = target.timeouts().solve;
        match target.link_mut().request_within(&request, timeout)? {
            Response::LiveFrame(report) => Ok(report),
            other => Err(LinkError::Protocol {
                request: "DynamicFrame",
                expected: "LiveFrame",
                got: format!("{other:?}"),
            }),
        }
    }
}

/// The uniform nodal mass, where the target's step is the host's: backward Euler, one S for
/// the three directions, one mass for every node and 1 to [`MAX_TOOL_NODES`] tool nodes.
fn supported_mass(
    system: &DynamicSystem,
    matrices: &StepMatrices,
    tools: &[usize],
) -> Result<f64, ResidentError> {
    if matrices.scheme != Scheme::BackwardEuler {
        return Err(ResidentError::Scheme(matrices.scheme));
    }
    if matrices.groups.len() != 1 {
        return Err(ResidentError::Anisotropic);
    }
    let mass = system.mass().first().copied().unwrap_or(0.0);
    if system.mass().iter().any(|&m| m != mass) {
        return Err(ResidentError::NonUniformMass);
    }
    if tools.is_empty() || tools.len() > MAX_TOOL_NODES {
        return Err(ResidentError::ToolCount(tools.len()));
    }
    Ok(mass)
}

/// S (already scaled) encoded with `layout`, and K's raw values on S's words. A mirrored word
/// stands for its mirror too, which K must then equal; where it does not, S is encoded whole.
fn encode_s_and_k(
    s_up: &Csr,
    k_at: &dyn Fn(usize, usize) -> f64,
    k_frac: u8,
    layout: &EncodeOptions,
) -> Result<(EncodedMatrix, Vec<i32>), ResidentError> {
    let matrix = encode_with(s_up, layout)?.matrix;
    if !matrix.tiles.iter().any(|t| t.mirrored) || mirrors_agree(&matrix, k_at) {
        let stiffness = stiffness_values(&matrix, k_at, k_frac)?;
        return Ok((matrix, stiffness));
    }
    let whole = EncodeOptions {
        use_symmetry: false,
        ..*layout
    };
    let matrix = encode_with(s_up, &whole)?.matrix;
    let stiffness = stiffness_values(&matrix, k_at, k_frac)?;
    Ok((matrix, stiffness))
}

/// What a tool node's rows keep: the couplings to free nodes and to the other tool nodes.
struct ToolRows<'a> {
    constrained: &'a [bool],
    tools: &'a [usize],
}

impl ToolRows<'_> {
    /// Row `t` of `m`·2^scale in Q-format `frac`: its diagonal and the couplings kept.
    fn row(&self, m: &Csr, scale: i32, frac: u8, t: usize) -> Result<ToolRow, ResidentError> {
        let (cols, vals) = m.row(t);
        let mut out = ToolRow {
            node: t as u32,
            diagonal: 0,
            row: heapless::Vec::new(),
        };
        for (&j, &v) in cols.iter().zip(vals) {
            let raw = quantize(v * 2f64.powi(scale), frac)?;
            if j == t {
                out.diagonal = raw;
            } else if !self.constrained[j] || self.tools.contains(&j) {
                let coupling = Coupling {
                    column: j as u32,
                    value: raw,
                };
                out.row
                    .push(coupling)
                    .map_err(|_| ResidentError::RowTooLong {
                        node: t,
                        count: cols.len(),
                    })?;
            }
        }
        Ok(out)
    }
}

/// K's row `k` over the same columns as S's row `s` (K is zero where S is, off the diagonal).
fn on_columns_of(mut k: ToolRow, s: &ToolRow) -> ToolRow {
    let value_at = |column: u32| {
        k.row
            .iter()
            .find(|kc| kc.column == column)
            .map_or(0, |kc| kc.value)
    };
    let row = s
        .row
        .iter()
        .map(|cp| Coupling {
            column: cp.column,
            value: value_at(cp.column),
        })
        .collect();
    k.row = row;
    k
}

/// K's raw value at every word of `matrix` (0 on empty-row words).
fn stiffness_values(
    matrix: &EncodedMatrix,
    k_at: &dyn Fn(usize, usize) -> f64,
    frac_bits: u8,
) -> Result<Vec<i32>, QFormatError> {
    let mut out = Vec::with_capacity(matrix.words.len());
    for (header, words) in matrix.tile_words() {
        let mut row = header.row_base as usize;
        for &bits in words {
            let word = Word(bits);
            let column = header.col_base as usize + word.column() as usize;
            out.push(if word.raw_value() == 0 {
                0
            } else {
                quantize(k_at(row, column), frac_bits)?
            });
            row += word.end_of_row() as usize;
        }
    }
    Ok(out)
}

/// K equals itself at every mirrored word's mirror position.
fn mirrors_agree(matrix: &EncodedMatrix, k_at: &dyn Fn(usize, usize) -> f64) -> bool {
    let n = matrix.n as usize;
    matrix.tile_words().all(|(header, words)| {
        let mut row = header.row_base as usize;
        words.iter().all(|&bits| {
            let word = Word(bits);
            let column = header.col_base as usize + word.column() as usize;
            let ok = !header.mirrored || k_at(row, column) == k_at(n - 1 - row, n - 1 - column);
            row += word.end_of_row() as usize;
            ok
        })
    })
}

/// A's entry (i, j), 0 where it has none.
fn entry(a: &Csr, i: usize, j: usize) -> f64 {
    let (cols, vals) = a.row(i);
    cols.iter().position(|&c| c == j).map_or(0.0, |k| vals[k])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scale_puts_the_largest_entry_in_the_top_binade() {
        for max in [0.005, 0.5, 0.75, 1.0, 3.0, 1e-9, 12345.0] {
            let k = scale_up(max);
            let scaled = max * 2f64.powi(k);
            assert!((0.5..1.0).contains(&scaled), "{max}: {scaled}");
        }
    }
}
