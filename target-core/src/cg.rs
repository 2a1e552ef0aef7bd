//! Conjugate gradients on the target (thesis 2.3, 4.2), in block floating point.
//!
//! # Number formats
//!
//! - Matrix values are raw 21-bit integers q with value = q · 2^-F (`frac_bits` = F).
//! - Every vector is a [`deform_shared::qformat`] block: `i32` mantissas with one shared exponent.
//!   Mantissas are kept below 2^29 in magnitude (one more bit of headroom than the wire format).
//! - Scalars (α, β, norms) are computed once per iteration in `f64` (soft float on rv32imac:
//!   a few hundred instructions per iteration, nothing per element), then turned back into a
//!   mantissa/exponent pair for the vector loops.
//!
//! # Why this never overflows
//!
//! The MVU accumulates Σ q·p exactly in `i64`: |q| < 2^20, |p| < 2^30 and at most 512 terms per
//! tile row stay below 2^59. pᵀKp is accumulated exactly in `i128`. Each SVU update
//! `y ← a·u + b·y` first bounds its result, |a|·max|u| + |b|·max|y|, from the tracked maxima, and
//! picks the output exponent so that the bound is below 2^29: no element can exceed it, so there is
//! nothing to saturate. Because the maxima are measured after every update, the exponent follows
//! the vector down as the residual shrinks, and each vector keeps ~29 significant bits relative to
//! its largest element. That is what lets the fixed-point iteration go on converging where a single
//! static Q-format would stall.

use deform_shared::matrix::TileHeader;
use deform_shared::protocol::{
    DirectionReport, IterationCost, PhaseCounters, SolveFailure, SolveParams, SolveReport, Start,
};
use deform_shared::qformat::{block_exponent, floor_log2, ldexp, to_mantissa};
use deform_shared::word::{COLUMN_WINDOW, ER_BIT, VALUE_BITS};

/// Mantissas produced by the SVU stay below 2^OUTPUT_BITS.
const OUTPUT_BITS: i32 = 29;

/// A validated matrix as the MVUs see it.
#[derive(Clone, Copy)]
pub struct Matrix<'a> {
    pub n: usize,
    pub frac_bits: u8,
    pub tiles: &'a [TileHeader],
    /// All tiles' words, back to back in tile order.
    pub words: &'a [u32],
}

/// The working vectors CG needs besides b and x.
///
/// `p` must hold at least n + [`COLUMN_WINDOW`] elements: the MVU reads a tile's 512-column window
/// of p as a fixed-size array, which is what lets the compiler drop the bounds check from the
/// inner loop (a 9-bit column can never index past 512). The elements past n are never read for a
/// validated matrix. `r` and `kp` need n elements.
pub struct Scratch<'a> {
    pub r: &'a mut [i32],
    pub p: &'a mut [i32],
    pub kp: &'a mut [i64],
}

/// Length `p` must have for a matrix of dimension `n`.
pub const fn direction_len(n: usize) -> usize {
    n + COLUMN_WINDOW as usize
}

/// Reads the cycle and retired-instruction counters, so that the solver can charge each phase.
pub trait PhaseClock {
    fn now(&self) -> PhaseCounters;
}

/// A clock that always reads zero, for hosts and tests.
pub struct NoClock;
impl PhaseClock for NoClock {
    fn now(&self) -> PhaseCounters {
        PhaseCounters::default()
    }
}

/// Adds the counters elapsed since `since` to `total`.
fn charge(total: &mut PhaseCounters, since: PhaseCounters, clock: &impl PhaseClock) {
    let now = clock.now();
    total.cycles += now.cycles.wrapping_sub(since.cycles);
    total.instructions += now.instructions.wrapping_sub(since.instructions);
}

/// A number as mantissa · 2^exponent.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Scalar {
    m: i32,
    e: i32,
}

impl Scalar {
    const ONE: Scalar = Scalar { m: 1 << 29, e: -29 };

    fn from_f64(v: f64, extra_exponent: i32) -> Scalar {
        let e = block_exponent(v);
        // block_exponent guarantees the mantissa fits, so the fallback is unreachable.
        Scalar {
            m: to_mantissa(v, e).unwrap_or(0),
            e: e + extra_exponent,
        }
    }

    fn neg(self) -> Scalar {
        Scalar {
            m: -self.m,
            e: self.e,
        }
    }
}

/// Block-floating-point vector state besides its mantissas: exponent and current max |m|.
#[derive(Debug, Clone, Copy)]
struct Block {
    e: i32,
    max: u32,
}

fn max_abs(m: &[i32]) -> u32 {
    m.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0)
}

/// `v · 2^-s`, rounded to nearest, for a loop-invariant `s` of either sign.
#[inline(always)]
fn shift_round(v: i64, s: i32) -> i64 {
    if s > 0 {
        if s >= 63 {
            0
        } else {
            (v + (1i64 << (s - 1))) >> s
        }
    } else {
        v << (-s).min(62)
    }
}

/// What `y ← a·u + b·y` reads `u` from: another block vector, or the MVU's raw `i64` results
/// pre-shifted to 32 bits.
trait Source {
    fn get(&self, i: usize) -> i32;
}

struct Mantissas<'a>(&'a [i32]);
impl Source for Mantissas<'_> {
    #[inline(always)]
    fn get(&self, i: usize) -> i32 {
        self.0[i]
    }
}

struct Wide<'a> {
    values: &'a [i64],
    shift: u32,
}
impl Source for Wide<'_> {
    #[inline(always)]
    fn get(&self, i: usize) -> i32 {
        (self.values[i] >> self.shift) as i32
    }
}

/// Result of one SVU update: the new state of y and Σ y_i² of its mantissas (exact).
struct Update {
    block: Block,
    sum_sq: u128,
}

/// The SVU's one vector operation, `y ← a·u + b·y`, element by element, returning y's new
/// exponent, its max and its squared norm (all in the same pass).
fn axpby(
    y: &mut [i32],
    y_block: Block,
    b: Scalar,
    a: Scalar,
    u: &impl Source,
    u_block: Block,
) -> Update {
    // Exponents of the two products a·u_i and b·y_i, and the bound on |a·u_i + b·y_i|.
    let e1 = a.e + u_block.e;
    let e2 = b.e + y_block.e;
    let t1 = a.m.unsigned_abs() as u64 * u_block.max as u64;
    let t2 = b.m.unsigned_abs() as u64 * y_block.max as u64;
    if t1 == 0 && t2 == 0 {
        y.fill(0);
        return Update {
            block: Block { e: 0, max: 0 },
            sum_sq: 0,
        };
    }
    let top = e1.max(e2);
    let bound = ldexp(t1 as f64, e1 - top) + ldexp(t2 as f64, e2 - top);
    let ez = top + floor_log2(bound) + 1 - OUTPUT_BITS;
    let (s1, s2) = (ez - e1, ez - e2);
    let (am, bm) = (a.m as i64, b.m as i64);
    let mut max = 0u32;
    let mut sum_sq = 0u128;
    for (i, yi) in y.iter_mut().enumerate() {
        let z = shift_round(am * u.get(i) as i64, s1) + shift_round(bm * *yi as i64, s2);
        let z = z as i32;
        *yi = z;
        max = max.max(z.unsigned_abs());
        sum_sq += (z as i64 * z as i64) as u64 as u128;
    }
    Update {
        block: Block { e: ez, max },
        sum_sq,
    }
}

/// What one matrix–vector product yields besides Kp itself.
struct MvuResult {
    /// pᵀKp over the mantissas, exact; its exponent is 2·e_p − F.
    p_kp: i128,
    /// max |(Kp)_i| over the raw accumulators.
    max: u64,
}

/// The MVU (thesis 4.2.1): executes every tile's instruction words against p, writing
/// y = Kp (raw, exponent e_p − F) and accumulating pᵀKp as each row completes.
fn mvu(a: &Matrix<'_>, p: &[i32], y: &mut [i64]) -> MvuResult {
    y.fill(0);
    let mut p_kp: i128 = 0;
    let mut start = 0usize;
    for tile in a.tiles {
        let end = start + tile.words as usize;
        let words = a.words.get(start..end).unwrap_or(&[]);
        start = end;
        let col_base = tile.col_base as usize;
        let Some(window) = p
            .get(col_base..col_base + COLUMN_WINDOW as usize)
            .and_then(|w| <&[i32; COLUMN_WINDOW as usize]>::try_from(w).ok())
        else {
            continue;
        };
        let mut row = tile.row_base as usize;
        let mut acc: i64 = 0;
        let mut mirror_acc: i64 = 0;
        let n = a.n;
        for &w in words {
            let column = ((w >> VALUE_BITS) as usize) & (COLUMN_WINDOW as usize - 1);
            let value = ((w << (32 - VALUE_BITS)) as i32) >> (32 - VALUE_BITS);
            acc += value as i64 * window[column] as i64;
            if tile.mirrored {
                // Validated columns are < n, so the mirrored column exists.
                let mirror = (n - 1).wrapping_sub(col_base + column);
                mirror_acc += value as i64 * p.get(mirror).copied().unwrap_or(0) as i64;
            }
            if w & ER_BIT != 0 {
                p_kp += add_row(y, p, row, acc);
                if tile.mirrored {
                    p_kp += add_row(y, p, (n - 1).wrapping_sub(row), mirror_acc);
                }
                acc = 0;
                mirror_acc = 0;
                row += 1;
            }
        }
    }
    let max = y.iter().map(|v| v.unsigned_abs()).max().unwrap_or(0);
    MvuResult { p_kp, max }
}

/// Adds a finished row sum to y[row] and returns its share p_row·acc of pᵀKp (exact).
fn add_row(y: &mut [i64], p: &[i32], row: usize, acc: i64) -> i128 {
    let (Some(out), Some(&pi)) = (y.get_mut(row), p.get(row)) else {
        return 0;
    };
    *out += acc;
    // p_i · acc exactly: acc is split so that both products fit i64.
    let lo = (pi as i64) * (acc as u32 as i64);
    let hi = (pi as i64) * (acc >> 32);
    ((hi as i128) << 32) + lo as i128
}

/// The shift that brings raw MVU results below 2^30, and their max after it.
fn narrow(max: u64) -> (u32, u32) {
    let bits = 64 - max.leading_zeros();
    let shift = bits.saturating_sub(30);
    (shift, (max >> shift) as u32)
}

/// √x for x ≥ 0 without std: Newton's method from a power-of-two first guess.
fn sqrt(x: f64) -> f64 {
    if x <= 0.0 || !x.is_finite() {
        return if x == 0.0 { 0.0 } else { x.max(0.0) };
    }
    let mut g = ldexp(1.0, floor_log2(x) / 2);
    for _ in 0..8 {
        g = 0.5 * (g + x / g);
    }
    g
}

/// Solves A x = b. `b` and `x` are block-floating-point vectors (value = m · 2^exponent);
/// `x`/`x_exponent` hold x₀ on entry when `params.start` is not [`Start::Zero`], and the
/// solution on return. The report's `residual` is the recursive ‖r‖/‖b‖.
#[allow(clippy::too_many_arguments)]
pub fn solve(
    a: &Matrix<'_>,
    b: &[i32],
    b_exponent: i32,
    x: &mut [i32],
    x_exponent: &mut i32,
    scratch: Scratch<'_>,
    params: &SolveParams,
    clock: &impl PhaseClock,
) -> Result<SolveReport, SolveFailure> {
    let n = a.n;
    let f = a.frac_bits as i32;
    let (Some(b), Some(x), Some(r), Some(p), Some(kp)) = (
        b.get(..n),
        x.get_mut(..n),
        scratch.r.get_mut(..n),
        scratch.p.get_mut(..direction_len(n)),
        scratch.kp.get_mut(..n),
    ) else {
        return Err(SolveFailure::WorkspaceTooSmall);
    };
    let mut report = SolveReport {
        iterations: 0,
        converged: false,
        residual: 0.0,
        directions: heapless::Vec::new(),
        words_per_iteration: a.words.len() as u32,
        mvus: 1,
        overlapping: false,
        mvu: PhaseCounters::default(),
        svu: PhaseCounters::default(),
        per_iteration: IterationCost::default(),
        saturations: 0,
    };

    let t = clock.now();
    let b_block = Block {
        e: b_exponent,
        max: max_abs(b),
    };
    let bb: u128 = b
        .iter()
        .map(|&v| (v as i64 * v as i64) as u64 as u128)
        .sum();
    if bb == 0 {
        x.fill(0);
        *x_exponent = 0;
        report.converged = true;
        let _ = report.directions.push(DirectionReport {
            iterations: 0,
            converged: true,
            residual: 0.0,
        });
        charge(&mut report.svu, t, clock);
        return Ok(report);
    }
    if params.start == Start::Zero {
        x.fill(0);
        *x_exponent = 0;
    }
    let mut x_block = Block {
        e: *x_exponent,
        max: max_abs(x),
    };
    // Squared norm of b in f64 units relative to 2^(2·e_b); residual ratios use this.
    let bb_f = bb as f64;
    // ‖r‖² / ‖b‖² for a residual block with exponent e_r and Σm² = rr.
    let ratio = |rr: u128, e_r: i32| ldexp(rr as f64 / bb_f, 2 * (e_r - b_exponent));
    let tol_sq = params.tolerance * params.tolerance;

    // r₀ = b − A x₀.
    r.copy_from_slice(b);
    let mut r_update = Update {
        block: b_block,
        sum_sq: bb,
    };
    charge(&mut report.svu, t, clock);
    if x_block.max != 0 {
        let t = clock.now();
        let (head, _) = p.split_at_mut(n);
        head.copy_from_slice(x);
        let ax = mvu(a, p, kp);
        charge(&mut report.mvu, t, clock);
        let t = clock.now();
        let (shift, max) = narrow(ax.max);
        let u_block = Block {
            e: x_block.e - f + shift as i32,
            max,
        };
        r_update = axpby(
            r,
            b_block,
            Scalar::ONE,
            Scalar::ONE.neg(),
            &Wide { values: kp, shift },
            u_block,
        );
        charge(&mut report.svu, t, clock);
    }
    let t = clock.now();
    let mut r_block = r_update.block;
    let mut rr = r_update.sum_sq;
    // p₀ = r₀.
    p[..n].copy_from_slice(r);
    let mut p_block = r_block;
    let mut residual_sq = ratio(rr, r_block.e);
    charge(&mut report.svu, t, clock);

    while residual_sq > tol_sq && report.iterations < params.max_iterations {
        let t = clock.now();
        let mvu_out = mvu(a, p, kp);
        charge(&mut report.mvu, t, clock);

        let t = clock.now();
        report.iterations += 1;
        if mvu_out.p_kp <= 0 {
            return Err(SolveFailure::NotPositiveDefinite {
                iteration: report.iterations,
            });
        }
        // α = rᵀr / pᵀKp; exponents: 2e_r and 2e_p − F.
        let alpha = Scalar::from_f64(
            rr as f64 / mvu_out.p_kp as f64,
            2 * r_block.e - 2 * p_block.e + f,
        );
        let (head, _) = p.split_at_mut(n);
        // x ← x + α p
        x_block = axpby(x, x_block, Scalar::ONE, alpha, &Mantissas(head), p_block).block;
        // r ← r − α Kp
        let (shift, kp_max) = narrow(mvu_out.max);
        let kp_block = Block {
            e: p_block.e - f + shift as i32,
            max: kp_max,
        };
        let update = axpby(
            r,
            r_block,
            Scalar::ONE,
            alpha.neg(),
            &Wide { values: kp, shift },
            kp_block,
        );
        // β = r_newᵀr_new / rᵀr
        let beta = Scalar::from_f64(
            update.sum_sq as f64 / rr as f64,
            2 * update.block.e - 2 * r_block.e,
        );
        r_block = update.block;
        rr = update.sum_sq;
        residual_sq = ratio(rr, r_block.e);
        // p ← r + β p
        p_block = axpby(head, p_block, beta, Scalar::ONE, &Mantissas(r), r_block).block;
        charge(&mut report.svu, t, clock);
    }
    *x_exponent = x_block.e;
    report.converged = residual_sq <= tol_sq;
    report.residual = sqrt(residual_sq);
    let _ = report.directions.push(DirectionReport {
        iterations: report.iterations,
        converged: report.converged,
        residual: report.residual,
    });
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use deform_shared::matrix::validate_tile;
    use deform_shared::qformat::{from_mantissa, quantize};
    use deform_shared::word::Word;
    use proptest::prelude::*;

    /// A sparse matrix as rows of (column, value) in f64, with the tiles and words encoding it.
    struct Encoded {
        n: usize,
        frac_bits: u8,
        tiles: Vec<TileHeader>,
        words: Vec<u32>,
        rows: Vec<Vec<(usize, f64)>>,
    }

    /// Row blocks of `block` rows, each with the window starting at its smallest column.
    fn encode(rows: Vec<Vec<(usize, f64)>>, frac_bits: u8, block: usize) -> Encoded {
        let n = rows.len();
        let mut tiles = Vec::new();
        let mut words = Vec::new();
        for start in (0..n).step_by(block) {
            let end = (start + block).min(n);
            let col_base = rows[start..end]
                .iter()
                .flatten()
                .map(|&(c, _)| c)
                .min()
                .unwrap_or(0);
            let first = words.len();
            for row in &rows[start..end] {
                if row.is_empty() {
                    words.push(Word::empty_row(false).bits());
                }
                for (k, &(c, v)) in row.iter().enumerate() {
                    let raw = quantize(v, frac_bits).unwrap() as i64;
                    words.push(
                        Word::new((c - col_base) as u32, raw, k + 1 == row.len(), false)
                            .unwrap()
                            .bits(),
                    );
                }
            }
            *words.last_mut().unwrap() |= deform_shared::word::EM_BIT;
            let header = TileHeader {
                row_base: start as u32,
                col_base: col_base as u32,
                rows: (end - start) as u32,
                words: (words.len() - first) as u32,
                mvu: 0,
                mirrored: false,
            };
            validate_tile(tiles.len() as u32, &header, &words[first..], n as u32).unwrap();
            tiles.push(header);
        }
        Encoded {
            n,
            frac_bits,
            tiles,
            words,
            rows,
        }
    }

    fn laplacian_1d(n: usize) -> Vec<Vec<(usize, f64)>> {
        (0..n)
            .map(|i| {
                let mut row = Vec::new();
                if i > 0 {
                    row.push((i - 1, -1.0));
                }
                row.push((i, 2.0));
                if i + 1 < n {
                    row.push((i + 1, -1.0));
                }
                row
            })
            .collect()
    }

    /// Model-A Laplacian of an m³ grid with the 8 corners eliminated symmetrically.
    fn laplacian_3d(m: usize, k: f64) -> Vec<Vec<(usize, f64)>> {
        let idx = |i: usize, j: usize, l: usize| i + m * (j + m * l);
        let corner = |i: usize| i == 0 || i == m - 1;
        let fixed = |v: usize| corner(v % m) && corner((v / m) % m) && corner(v / (m * m));
        let mut rows = vec![Vec::new(); m * m * m];
        for l in 0..m {
            for j in 0..m {
                for i in 0..m {
                    let v = idx(i, j, l);
                    let mut diag = 0.0;
                    let mut row = Vec::new();
                    let mut nb = |c: usize| {
                        diag += k;
                        if !fixed(v) && !fixed(c) {
                            row.push((c, -k));
                        }
                    };
                    if i > 0 {
                        nb(idx(i - 1, j, l))
                    }
                    if i + 1 < m {
                        nb(idx(i + 1, j, l))
                    }
                    if j > 0 {
                        nb(idx(i, j - 1, l))
                    }
                    if j + 1 < m {
                        nb(idx(i, j + 1, l))
                    }
                    if l > 0 {
                        nb(idx(i, j, l - 1))
                    }
                    if l + 1 < m {
                        nb(idx(i, j, l + 1))
                    }
                    row.push((v, diag));
                    row.sort_by_key(|&(c, _)| c);
                    rows[v] = row;
                }
            }
        }
        rows
    }

    fn matvec(rows: &[Vec<(usize, f64)>], x: &[f64]) -> Vec<f64> {
        rows.iter()
            .map(|row| row.iter().map(|&(c, v)| v * x[c]).sum())
            .collect()
    }

    /// Plain f64 CG to a tight tolerance: the yardstick.
    fn reference(rows: &[Vec<(usize, f64)>], b: &[f64]) -> Vec<f64> {
        let n = b.len();
        let mut x = vec![0.0; n];
        let mut r = b.to_vec();
        let mut p = r.clone();
        let mut rr: f64 = r.iter().map(|v| v * v).sum();
        let bb = rr;
        for _ in 0..10 * n {
            if rr <= 1e-28 * bb {
                break;
            }
            let kp = matvec(rows, &p);
            let alpha = rr / p.iter().zip(&kp).map(|(a, b)| a * b).sum::<f64>();
            for i in 0..n {
                x[i] += alpha * p[i];
                r[i] -= alpha * kp[i];
            }
            let rr_new: f64 = r.iter().map(|v| v * v).sum();
            for i in 0..n {
                p[i] = r[i] + rr_new / rr * p[i];
            }
            rr = rr_new;
        }
        x
    }

    struct Run {
        x: Vec<f64>,
        report: SolveReport,
    }

    fn run(m: &Encoded, b: &[f64], x0: Option<&[f64]>, tol: f64) -> Result<Run, SolveFailure> {
        let n = m.n;
        let to_block = |v: &[f64]| {
            let e = block_exponent(v.iter().fold(0.0f64, |a, b| a.max(b.abs())));
            (
                v.iter()
                    .map(|&x| to_mantissa(x, e).unwrap())
                    .collect::<Vec<_>>(),
                e,
            )
        };
        let (bm, be) = to_block(b);
        let (mut xm, mut xe) = x0.map(to_block).unwrap_or((vec![0; n], 0));
        let (mut r, mut p, mut kp) = (vec![0; n], vec![0; direction_len(n)], vec![0; n]);
        let matrix = Matrix {
            n,
            frac_bits: m.frac_bits,
            tiles: &m.tiles,
            words: &m.words,
        };
        let start = if x0.is_some() {
            Start::Uploaded
        } else {
            Start::Zero
        };
        let params = SolveParams {
            max_iterations: 10 * n as u32,
            tolerance: tol,
            start,
            directions: 1,
        };
        let report = solve(
            &matrix,
            &bm,
            be,
            &mut xm,
            &mut xe,
            Scratch {
                r: &mut r,
                p: &mut p,
                kp: &mut kp,
            },
            &params,
            &NoClock,
        )?;
        Ok(Run {
            x: xm.iter().map(|&v| from_mantissa(v, xe)).collect(),
            report,
        })
    }

    fn max_rel_err(x: &[f64], reference: &[f64]) -> f64 {
        let scale = reference.iter().fold(0.0f64, |a, b| a.max(b.abs()));
        x.iter()
            .zip(reference)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max)
            / scale
    }

    fn true_residual(rows: &[Vec<(usize, f64)>], x: &[f64], b: &[f64]) -> f64 {
        let kx = matvec(rows, x);
        let rr: f64 = kx.iter().zip(b).map(|(a, b)| (a - b) * (a - b)).sum();
        (rr / b.iter().map(|v| v * v).sum::<f64>()).sqrt()
    }

    #[test]
    fn solves_a_1d_laplacian_like_f64() {
        let m = encode(laplacian_1d(60), 18, 64);
        let b: Vec<f64> = (0..60).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
        let run = run(&m, &b, None, 1e-9).unwrap();
        assert!(run.report.converged, "{:?}", run.report);
        let err = max_rel_err(&run.x, &reference(&m.rows, &b));
        assert!(err < 1e-7, "max relative error {err:e}");
        assert!(true_residual(&m.rows, &run.x, &b) < 1e-7);
    }

    #[test]
    fn solves_the_thesis_cube_across_tiles() {
        // 10³ model A, k = 1, corner nodes fixed, 1 N at (0, 5, 5): thesis 2.6, x direction.
        let rows = laplacian_3d(10, 1.0);
        let m = encode(rows, 17, 250);
        assert_eq!(m.tiles.len(), 4);
        let mut b = vec![0.0; 1000];
        b[5 * 10 + 5 * 100] = 1.0; // node (0, 5, 5)
        let run = run(&m, &b, None, 1e-9).unwrap();
        assert!(run.report.converged, "{:?}", run.report);
        let reference = reference(&m.rows, &b);
        let err = max_rel_err(&run.x, &reference);
        assert!(
            err < 1e-6,
            "max relative error {err:e} after {} iterations",
            run.report.iterations
        );
        assert_eq!(run.report.words_per_iteration as usize, m.words.len());
    }

    #[test]
    fn warm_start_from_the_answer_needs_fewer_iterations() {
        let m = encode(laplacian_3d(6, 1.0), 17, 216);
        let mut b = vec![0.0; 216];
        b[100] = 1.0;
        b[7] = -0.5;
        let cold = run(&m, &b, None, 1e-8).unwrap();
        let warm = run(&m, &b, Some(&cold.x), 1e-8).unwrap();
        assert!(
            warm.report.iterations * 2 < cold.report.iterations,
            "{} vs {}",
            warm.report.iterations,
            cold.report.iterations
        );
        assert!(max_rel_err(&warm.x, &reference(&m.rows, &b)) < 1e-6);
    }

    #[test]
    fn scale_of_the_load_does_not_matter() {
        let m = encode(laplacian_1d(30), 18, 30);
        for scale in [1e-30, 1e-6, 1.0, 1e9, 1e30] {
            let b: Vec<f64> = (0..30).map(|i| scale * (1.0 + (i % 5) as f64)).collect();
            let run = run(&m, &b, None, 1e-9).unwrap();
            let err = max_rel_err(&run.x, &reference(&m.rows, &b));
            assert!(err < 1e-7, "scale {scale:e}: error {err:e}");
        }
    }

    #[test]
    fn fractional_values_use_their_q_format() {
        // tridiag(-0.3, 0.75, -0.3): SPD with non-integer entries.
        let rows: Vec<Vec<(usize, f64)>> = laplacian_1d(40)
            .into_iter()
            .map(|r| {
                r.into_iter()
                    .map(|(c, v)| (c, if v > 0.0 { 0.75 } else { -0.3 }))
                    .collect()
            })
            .collect();
        let m = encode(rows, 20, 40);
        let b: Vec<f64> = (0..40).map(|i| (i as f64).sin()).collect();
        let run = run(&m, &b, None, 1e-10).unwrap();
        // The quantized matrix is what the target solves; compare against it.
        let q = m
            .rows
            .iter()
            .map(|r| {
                r.iter()
                    .map(|&(c, v)| (c, (v * 1048576.0f64).round() / 1048576.0))
                    .collect()
            })
            .collect::<Vec<Vec<_>>>();
        assert!(max_rel_err(&run.x, &reference(&q, &b)) < 1e-7);
    }

    #[test]
    fn zero_load_gives_zero_displacement() {
        let m = encode(laplacian_1d(10), 18, 10);
        let run = run(&m, &[0.0; 10], Some(&[1.0; 10]), 1e-9).unwrap();
        assert!(run.report.converged);
        assert!(run.x.iter().all(|&v| v == 0.0));
    }

    #[test]
    fn indefinite_matrix_is_reported() {
        let rows: Vec<Vec<(usize, f64)>> = (0..8)
            .map(|i| vec![(i, if i == 3 { -1.0 } else { 1.0 })])
            .collect();
        let m = encode(rows, 18, 8);
        let mut b = vec![0.0; 8];
        b[3] = 1.0;
        assert!(matches!(
            run(&m, &b, None, 1e-9),
            Err(SolveFailure::NotPositiveDefinite { iteration: 1 })
        ));
    }

    #[test]
    fn short_workspace_is_an_error_not_a_panic() {
        let m = encode(laplacian_1d(10), 18, 10);
        let matrix = Matrix {
            n: 10,
            frac_bits: 18,
            tiles: &m.tiles,
            words: &m.words,
        };
        let (mut x, mut xe) = (vec![0; 10], 0);
        let params = SolveParams {
            max_iterations: 5,
            tolerance: 1e-6,
            start: Start::Zero,
            directions: 1,
        };
        let out = solve(
            &matrix,
            &[1; 10],
            0,
            &mut x,
            &mut xe,
            Scratch {
                r: &mut [0; 10],
                p: &mut [0; 10],
                kp: &mut [0; 10],
            },
            &params,
            &NoClock,
        );
        assert_eq!(out, Err(SolveFailure::WorkspaceTooSmall));
    }

    #[test]
    fn iteration_cap_is_honoured() {
        let m = encode(laplacian_1d(100), 18, 100);
        let n = 100;
        let matrix = Matrix {
            n,
            frac_bits: 18,
            tiles: &m.tiles,
            words: &m.words,
        };
        let (mut x, mut xe) = (vec![0; n], 0);
        let params = SolveParams {
            max_iterations: 3,
            tolerance: 1e-12,
            start: Start::Zero,
            directions: 1,
        };
        let report = solve(
            &matrix,
            &vec![1 << 20; n],
            0,
            &mut x,
            &mut xe,
            Scratch {
                r: &mut vec![0; n],
                p: &mut vec![0; direction_len(n)],
                kp: &mut vec![0; n],
            },
            &params,
            &NoClock,
        )
        .unwrap();
        assert_eq!(report.iterations, 3);
        assert!(!report.converged && report.residual > 1e-12);
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(64))]
        #[test]
        fn random_spd_systems_match_f64(
            n in 2usize..40,
            diag in proptest::collection::vec(2.5f64..6.0, 40),
            off in proptest::collection::vec(-1.0f64..1.0, 40),
            b in proptest::collection::vec(-1.0e3f64..1.0e3, 40),
        ) {
            // Diagonally dominant symmetric tridiagonal: SPD.
            let rows: Vec<Vec<(usize, f64)>> = (0..n).map(|i| {
                let mut row = Vec::new();
                if i > 0 { row.push((i - 1, off[i - 1])); }
                row.push((i, diag[i]));
                if i + 1 < n { row.push((i + 1, off[i])); }
                row
            }).collect();
            let m = encode(rows, 17, 7);
            let q: Vec<Vec<(usize, f64)>> = m.rows.iter().map(|r| r.iter().map(|&(c, v)| (c, quantize(v, 17).unwrap() as f64 / 131072.0)).collect()).collect();
            let b = &b[..n];
            prop_assume!(b.iter().any(|&v| v != 0.0));
            let run = run(&m, b, None, 1e-10).unwrap();
            prop_assert!(run.report.converged);
            let tr = true_residual(&q, &run.x, b);
            prop_assert!(tr < 1e-7, "true residual {tr:e}, report {:?}", run.report);
        }
    }
}
