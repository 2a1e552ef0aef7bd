//! The MVU inner loop (thesis 4.2.1): one tile's instruction words against the search
//! directions.
//!
//! # Layout it relies on
//!
//! - The search directions of all fused systems are interleaved, `p[i] = [p₀ᵢ, p₁ᵢ, p₂ᵢ, pad]`
//!   ([`Lanes`], 16 bytes), so that one address computed from a word's column serves all three
//!   loads with immediate offsets 0, 4, 8. The byte offset of column c is `16·c`, which is
//!   `(w >> 17) & 0x1FF0` of the word `w`: two instructions.
//! - Row sums go to `y[row] : [i64; 3]` ([`Sums`]), one per direction.
//!
//! # Numerics
//!
//! Each product q·p (|q| < 2^20, |p| < 2^30) is exact in `i64`, and so is the row sum (at most
//! 2^12 products of a tile row before the sum could reach 2^62; validated tiles have at most
//! 512 columns per row, and [`crate::cg::plan`] refuses a matrix whose rows could overflow).
//! pᵀKp is accumulated exactly in `i128` as each row ends. Nothing is rounded.
//!
//! # Loop shape
//!
//! Per word: load it, extract the column byte offset (2 ops) and add the base, sign-extend the
//! value (`slli 11`, `srai 11`), then per direction one load and an exact 64-bit
//! multiply–accumulate (`mul`, `mulh`, `add`, `sltu`, `add`, `add`), step the word pointer and
//! branch back unless the word has ER (an unsigned compare `w < 2^30` tests ER and EM at
//! once, since a validated tile sets EM only on a word that also has ER). A mirrored tile adds
//! a second address (`p[n−1−col_base] − 16·c`) and a second set of accumulators.
#![allow(unsafe_code)]

use deform_shared::protocol::MAX_DIRECTIONS;
use deform_shared::word::ER_BIT;

/// One node's search-direction mantissas of every fused direction, plus padding to 16 bytes.
pub type Lanes = [i32; 4];
/// One row's MVU results, one per direction.
pub type Sums = [i64; MAX_DIRECTIONS];

/// Where one tile's words read and write. All pointers are into the solver's buffers.
#[derive(Clone, Copy)]
pub struct TileRun {
    /// The tile's first word.
    pub words: *const u32,
    /// Rows in the tile (ER words to go).
    pub rows: u32,
    /// `&p[col_base]`: column c of the tile reads `p[col_base + c]`.
    pub p_cols: *const Lanes,
    /// `&p[n − 1 − col_base]`: a mirrored word reads `p[n − 1 − col_base − c]`.
    pub p_mirror_cols: *const Lanes,
    /// Where row `row_base`'s sums go; the next row's are one further.
    pub y: *mut Sums,
    /// Where the mirror row `n − 1 − row_base`'s sums go; the next tile row's mirror is one
    /// slot *lower*.
    pub y_mirror: *mut Sums,
    /// `&p[row_base]`, for pᵀKp.
    pub p_row: *const Lanes,
    /// `&p[n − 1 − row_base]`, for pᵀKp of the mirror rows.
    pub p_mirror_row: *const Lanes,
}

/// p_i · acc exactly, as an `i128`, without a 128-bit multiply (which rv32 does in software):
/// acc is split into its high and low 32 bits, each product fits `i64`.
#[inline(always)]
fn exact_product(p: i32, acc: i64) -> i128 {
    let lo = (p as i64) * (acc as u32 as i64);
    let hi = (p as i64) * (acc >> 32);
    ((hi as i128) << 32) + lo as i128
}

/// Runs one tile for `D` fused directions (`MIRROR`: persymmetric half storage), adding each
/// row sum into `y` and p_row·(row sum) into `p_kp`.
///
/// # Safety
///
/// - The tile passed [`deform_shared::matrix::validate_tile`] for dimension n: `rows` ER words,
///   the last one ends the tile, every column c has `col_base + c < n`.
/// - `p_cols` is `&p[col_base]` and `p_row` is `&p[row_base]` of a `p` with at least n
///   elements; for `MIRROR`, `p_mirror_cols` is `&p[n − 1 − col_base]` and `p_mirror_row` is
///   `&p[n − 1 − row_base]`.
/// - `y` points at `rows` writable slots (and `y_mirror` at the top of `rows` slots going
///   down, for `MIRROR`) that no one else accesses during the call.
#[inline(always)]
pub unsafe fn run_tile<const D: usize, const MIRROR: bool>(
    t: &TileRun,
    p_kp: &mut [i128; MAX_DIRECTIONS],
) {
    let mut w = t.words;
    let mut y = t.y;
    let mut y_mirror = t.y_mirror;
    let mut p_row = t.p_row;
    let mut p_mirror_row = t.p_mirror_row;
    let cols = t.p_cols as *const u8;
    let mirror_cols = t.p_mirror_cols as *const u8;
    for _ in 0..t.rows {
        let mut acc = [0i64; D];
        let mut mirror_acc = [0i64; D];
        #[cfg(target_arch = "riscv32")]
        let in_assembly = D == 1 || D == 3;
        #[cfg(not(target_arch = "riscv32"))]
        let in_assembly = false;
        if in_assembly {
            #[cfg(target_arch = "riscv32")]
            {
                // SAFETY: as for `portable_row`, whose sums these compute exactly.
                w = unsafe {
                    if MIRROR {
                        riscv::mirrored_row(w, cols, mirror_cols, &mut acc, &mut mirror_acc)
                    } else {
                        riscv::row(w, cols, &mut acc)
                    }
                };
            }
        } else {
            // SAFETY: forwarded from the caller.
            w = unsafe {
                portable_row::<D, MIRROR>(w, cols, mirror_cols, &mut acc, &mut mirror_acc)
            };
        }
        // SAFETY: one slot per tile row, as the caller promised; p_row walks p[row_base..].
        unsafe {
            let (out, pi) = (&mut *y, &*p_row);
            for d in 0..D {
                out[d] += acc[d];
                p_kp[d] += exact_product(pi[d], acc[d]);
            }
        }
        y = y.wrapping_add(1);
        p_row = p_row.wrapping_add(1);
        if MIRROR {
            // SAFETY: as above, walking down from the mirror of row_base.
            unsafe {
                let (out, pi) = (&mut *y_mirror, &*p_mirror_row);
                for d in 0..D {
                    out[d] += mirror_acc[d];
                    p_kp[d] += exact_product(pi[d], mirror_acc[d]);
                }
            }
            y_mirror = y_mirror.wrapping_sub(1);
            p_mirror_row = p_mirror_row.wrapping_sub(1);
        }
    }
}

/// One row of a tile: adds its products into `acc` (and the mirrored ones into `mirror_acc`)
/// and returns the pointer past its ER word. The specification of the MVU loop.
///
/// # Safety
///
/// `w` points at a row of a validated tile; `cols` and `mirror_cols` are as in [`TileRun`].
#[inline(always)]
unsafe fn portable_row<const D: usize, const MIRROR: bool>(
    mut w: *const u32,
    cols: *const u8,
    mirror_cols: *const u8,
    acc: &mut [i64; D],
    mirror_acc: &mut [i64; D],
) -> *const u32 {
    loop {
        // SAFETY: the row has an ER word at or after `w`, inside the tile.
        let word = unsafe { *w };
        w = w.wrapping_add(1);
        let offset = ((word >> 17) & 0x1FF0) as usize;
        let value = (((word << 11) as i32) >> 11) as i64;
        // SAFETY: offset = 16·c with col_base + c < n, so this is p[col_base + c].
        let lanes = unsafe { &*(cols.wrapping_add(offset) as *const Lanes) };
        for d in 0..D {
            acc[d] += value * lanes[d] as i64;
        }
        if MIRROR {
            // SAFETY: n − 1 − col_base − c ≥ 0, so this is p[n − 1 − col_base − c].
            let mirrored = unsafe { &*(mirror_cols.wrapping_sub(offset) as *const Lanes) };
            for d in 0..D {
                mirror_acc[d] += value * mirrored[d] as i64;
            }
        }
        if word >= ER_BIT {
            return w;
        }
    }
}

/// [`run_tile`] for a run-time direction count (1..=3) and mirror flag.
///
/// # Safety
///
/// As [`run_tile`].
#[inline(never)]
pub unsafe fn run_tile_dyn(
    t: &TileRun,
    directions: usize,
    mirrored: bool,
    p_kp: &mut [i128; MAX_DIRECTIONS],
) {
    // SAFETY: forwarded contract.
    unsafe {
        match (directions, mirrored) {
            (1, false) => run_tile::<1, false>(t, p_kp),
            (2, false) => run_tile::<2, false>(t, p_kp),
            (1, true) => run_tile::<1, true>(t, p_kp),
            (2, true) => run_tile::<2, true>(t, p_kp),
            (_, false) => run_tile::<3, false>(t, p_kp),
            (_, true) => run_tile::<3, true>(t, p_kp),
        }
    }
}

/// The inner loop in RV32IM assembly, for one and for three directions: 15 instructions per
/// word for one direction, 29 per word (9.67 per multiply-accumulate) for three; mirrored
/// tiles 23 and 51 (11.5 and 8.5 per multiply-accumulate). Rust's code generation spills the six accumulator words of the fused loop and adds
/// a bounds-free but longer address computation; this is the loop the thesis's MVU pipeline
/// does in hardware. The portable loop in [`run_tile`] is the specification, and the HIL tests
/// check that the firmware's results equal the host's bit for bit.
#[cfg(target_arch = "riscv32")]
mod riscv {
    use super::{Lanes, ER_BIT};
    use core::arch::asm;

    /// Byte offset of column c in the interleaved p: `(w >> 17) & COLUMN_MASK` = 16·c.
    const COLUMN_MASK: u32 = 0x1FF0;

    /// Adds one row's products into `acc` (one or three directions) and returns the pointer to
    /// the word after the row's ER word.
    ///
    /// # Safety
    ///
    /// `w` points at a row of a validated tile and `cols` at p[col_base] (see
    /// [`super::run_tile`]).
    #[inline(always)]
    pub unsafe fn row<const D: usize>(
        w: *const u32,
        cols: *const u8,
        acc: &mut [i64; D],
    ) -> *const u32 {
        let _: *const Lanes = cols.cast();
        let mut wp = w;
        if D == 1 {
            let (mut lo, mut hi) = (0u32, 0u32);
            // SAFETY: reads only the row's words and p[col_base + c] for its columns.
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "srli {t}, {w}, 17",
                    "and {t}, {t}, {mask}",
                    "add {t}, {t}, {base}",
                    "lw {t}, 0({t})",
                    "slli {v}, {w}, 11",
                    "srai {v}, {v}, 11",
                    "mul {m}, {v}, {t}",
                    "mulh {v}, {v}, {t}",
                    "add {lo}, {lo}, {m}",
                    "sltu {m}, {lo}, {m}",
                    "add {hi}, {hi}, {v}",
                    "add {hi}, {hi}, {m}",
                    "addi {wp}, {wp}, 4",
                    "bltu {w}, {er}, 2b",
                    wp = inout(reg) wp,
                    lo = inout(reg) lo,
                    hi = inout(reg) hi,
                    base = in(reg) cols,
                    mask = in(reg) COLUMN_MASK,
                    er = in(reg) ER_BIT,
                    w = out(reg) _,
                    t = out(reg) _,
                    v = out(reg) _,
                    m = out(reg) _,
                    options(nostack, readonly),
                );
            }
            acc[0] = ((u64::from(hi) << 32) | u64::from(lo)) as i64;
        } else {
            let (mut l0, mut h0, mut l1, mut h1, mut l2, mut h2) =
                (0u32, 0u32, 0u32, 0u32, 0u32, 0u32);
            // SAFETY: as above; the three lanes of p[col_base + c] are at offsets 0, 4, 8.
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "srli {t}, {w}, 17",
                    "and {t}, {t}, {mask}",
                    "add {t}, {t}, {base}",
                    "slli {v}, {w}, 11",
                    "srai {v}, {v}, 11",
                    "lw {p}, 0({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {l0}, {l0}, {m}",
                    "sltu {m}, {l0}, {m}",
                    "add {h0}, {h0}, {p}",
                    "add {h0}, {h0}, {m}",
                    "lw {p}, 4({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {l1}, {l1}, {m}",
                    "sltu {m}, {l1}, {m}",
                    "add {h1}, {h1}, {p}",
                    "add {h1}, {h1}, {m}",
                    "lw {p}, 8({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {l2}, {l2}, {m}",
                    "sltu {m}, {l2}, {m}",
                    "add {h2}, {h2}, {p}",
                    "add {h2}, {h2}, {m}",
                    "addi {wp}, {wp}, 4",
                    "bltu {w}, {er}, 2b",
                    wp = inout(reg) wp,
                    l0 = inout(reg) l0,
                    h0 = inout(reg) h0,
                    l1 = inout(reg) l1,
                    h1 = inout(reg) h1,
                    l2 = inout(reg) l2,
                    h2 = inout(reg) h2,
                    base = in(reg) cols,
                    mask = in(reg) COLUMN_MASK,
                    er = in(reg) ER_BIT,
                    w = out(reg) _,
                    t = out(reg) _,
                    v = out(reg) _,
                    p = out(reg) _,
                    m = out(reg) _,
                    options(nostack, readonly),
                );
            }
            let sums = [join(l0, h0), join(l1, h1), join(l2, h2)];
            acc.copy_from_slice(&sums[..D]);
        }
        wp
    }

    fn join(lo: u32, hi: u32) -> i64 {
        ((u64::from(hi) << 32) | u64::from(lo)) as i64
    }

    /// [`row`] for a mirrored tile: each word also multiplies p[n − 1 − col_base − c] into the
    /// mirror row's sums. 23 instructions per word for one direction (11.5 per
    /// multiply-accumulate), 51 for three (8.5 per multiply-accumulate).
    ///
    /// # Safety
    ///
    /// As [`row`]; `mirror_cols` points at p[n − 1 − col_base].
    #[inline(always)]
    pub unsafe fn mirrored_row<const D: usize>(
        w: *const u32,
        cols: *const u8,
        mirror_cols: *const u8,
        acc: &mut [i64; D],
        mirror_acc: &mut [i64; D],
    ) -> *const u32 {
        let mut wp = w;
        if D == 1 {
            let (mut l0, mut h0, mut m0, mut n0) = (0u32, 0u32, 0u32, 0u32);
            // SAFETY: reads only the row's words, p[col_base + c] and p[n − 1 − col_base − c].
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "srli {t}, {w}, 17",
                    "and {t}, {t}, {mask}",
                    "sub {tm}, {mbase}, {t}",
                    "add {t}, {t}, {base}",
                    "slli {v}, {w}, 11",
                    "srai {v}, {v}, 11",
                    "lw {p}, 0({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {l0}, {l0}, {m}",
                    "sltu {m}, {l0}, {m}",
                    "add {h0}, {h0}, {p}",
                    "add {h0}, {h0}, {m}",
                    "lw {p}, 0({tm})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {m0}, {m0}, {m}",
                    "sltu {m}, {m0}, {m}",
                    "add {n0}, {n0}, {p}",
                    "add {n0}, {n0}, {m}",
                    "addi {wp}, {wp}, 4",
                    "bltu {w}, {er}, 2b",
                    wp = inout(reg) wp,
                    l0 = inout(reg) l0,
                    h0 = inout(reg) h0,
                    m0 = inout(reg) m0,
                    n0 = inout(reg) n0,
                    base = in(reg) cols,
                    mbase = in(reg) mirror_cols,
                    mask = in(reg) COLUMN_MASK,
                    er = in(reg) ER_BIT,
                    w = out(reg) _,
                    t = out(reg) _,
                    tm = out(reg) _,
                    v = out(reg) _,
                    p = out(reg) _,
                    m = out(reg) _,
                    options(nostack, readonly),
                );
            }
            acc[0] = join(l0, h0);
            mirror_acc[0] = join(m0, n0);
        } else {
            let mut a = [0u32; 12];
            // SAFETY: as above, three lanes at offsets 0, 4, 8 of both addresses.
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "srli {t}, {w}, 17",
                    "and {t}, {t}, {mask}",
                    "sub {tm}, {mbase}, {t}",
                    "add {t}, {t}, {base}",
                    "slli {v}, {w}, 11",
                    "srai {v}, {v}, 11",
                    "lw {p}, 0({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {a0}, {a0}, {m}",
                    "sltu {m}, {a0}, {m}",
                    "add {a1}, {a1}, {p}",
                    "add {a1}, {a1}, {m}",
                    "lw {p}, 4({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {a2}, {a2}, {m}",
                    "sltu {m}, {a2}, {m}",
                    "add {a3}, {a3}, {p}",
                    "add {a3}, {a3}, {m}",
                    "lw {p}, 8({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {a4}, {a4}, {m}",
                    "sltu {m}, {a4}, {m}",
                    "add {a5}, {a5}, {p}",
                    "add {a5}, {a5}, {m}",
                    "lw {p}, 0({tm})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {a6}, {a6}, {m}",
                    "sltu {m}, {a6}, {m}",
                    "add {a7}, {a7}, {p}",
                    "add {a7}, {a7}, {m}",
                    "lw {p}, 4({tm})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {a8}, {a8}, {m}",
                    "sltu {m}, {a8}, {m}",
                    "add {a9}, {a9}, {p}",
                    "add {a9}, {a9}, {m}",
                    "lw {p}, 8({tm})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "add {a10}, {a10}, {m}",
                    "sltu {m}, {a10}, {m}",
                    "add {a11}, {a11}, {p}",
                    "add {a11}, {a11}, {m}",
                    "addi {wp}, {wp}, 4",
                    "bltu {w}, {er}, 2b",
                    wp = inout(reg) wp,
                    a0 = inout(reg) a[0],
                    a1 = inout(reg) a[1],
                    a2 = inout(reg) a[2],
                    a3 = inout(reg) a[3],
                    a4 = inout(reg) a[4],
                    a5 = inout(reg) a[5],
                    a6 = inout(reg) a[6],
                    a7 = inout(reg) a[7],
                    a8 = inout(reg) a[8],
                    a9 = inout(reg) a[9],
                    a10 = inout(reg) a[10],
                    a11 = inout(reg) a[11],
                    base = in(reg) cols,
                    mbase = in(reg) mirror_cols,
                    mask = in(reg) COLUMN_MASK,
                    er = in(reg) ER_BIT,
                    w = out(reg) _,
                    t = out(reg) _,
                    tm = out(reg) _,
                    v = out(reg) _,
                    p = out(reg) _,
                    m = out(reg) _,
                    options(nostack, readonly),
                );
            }
            let own = [join(a[0], a[1]), join(a[2], a[3]), join(a[4], a[5])];
            let mirrored = [join(a[6], a[7]), join(a[8], a[9]), join(a[10], a[11])];
            acc.copy_from_slice(&own[..D]);
            mirror_acc.copy_from_slice(&mirrored[..D]);
        }
        wp
    }
}
