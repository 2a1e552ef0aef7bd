//! The MVU loops for RV32IM ([`super::run_tile`]'s `riscv` arm): one `asm!` block per
//! loop shape (directions, mirrored, split sums), scheduled for VexRiscv's pipeline; see the
//! parent module's documentation for the loop shape and the numerics.

use super::{
    column_offset_mask, column_offset_shift, rebuild_split, Lanes, COLUMN_OFFSET_MASK,
    COLUMN_OFFSET_SHIFT, ER_BIT, MAX_DIRECTIONS, VALUE_SIGN_SHIFT,
};
use core::arch::asm;

fn join(lo: u32, hi: u32) -> i64 {
    ((u64::from(hi) << 32) | u64::from(lo)) as i64
}

/// Adds one row's products into `acc` (`D` = 1, 2 or 3 directions) and returns the pointer
/// to the word after the row's ER word.
///
/// # Safety
///
/// `w` points at a row of a validated tile and `cols` at p[col_base] (see
/// [`super::run_tile`]), p being `1 << L` bytes a node with `4·D` ≤ `1 << L`.
#[inline(always)]
pub unsafe fn row<const D: usize, const SPLIT: bool, const L: u32>(
    w: *const u32,
    cols: *const u8,
    acc: &mut [i64; D],
) -> *const u32 {
    let _: *const Lanes = cols.cast();
    if SPLIT && D == 3 {
        let mut a = [0u32; 2 * MAX_DIRECTIONS];
        // SAFETY: forwarded; the caller allows split sums for these rows.
        let wp = unsafe { split_row3(w, cols, &mut a) };
        for (d, acc) in acc.iter_mut().enumerate() {
            *acc = rebuild_split(a[2 * d], a[2 * d + 1]);
        }
        return wp;
    }
    let mut wp = w;
    let mut a = [0u32; 2 * MAX_DIRECTIONS];
    match D {
        1 => {
            // Software-pipelined: a trip adds the previous word's product (m, hh; zero
            // before the first word) while its own word is decoded, so no result is used
            // within three slots of its load or multiply; the last product is added after
            // the loop. The loop's head is the pointer's step, which always assembles to a
            // 16-bit `c.addi`: the VexRiscv fetches aligned 32-bit words, and a taken
            // branch to a 32-bit instruction at an address 2 mod 4 cost a second fetch, a
            // bubble a word (a Verilator trace of the whole-K MVU phase, docs/PERFORMANCE.md,
            // "The VexRiscv's stalls, traced").
            // SAFETY: reads only the row's words and p[col_base + c] for its columns.
            unsafe {
                asm!(
                    "2:",
                    "addi {wp}, {wp}, 4",
                    "lw {w}, -4({wp})",
                    "add {l0}, {l0}, {m}",
                    "sltu {m}, {l0}, {m}",
                    "srli {t}, {w}, {cs}",
                    "slli {v}, {w}, {vs}",
                    "and {t}, {t}, {mask}",
                    "srai {v}, {v}, {vs}",
                    "add {t}, {t}, {base}",
                    "lw {t}, 0({t})",
                    "add {h0}, {h0}, {hh}",
                    "add {h0}, {h0}, {m}",
                    "mul {m}, {v}, {t}",
                    "mulh {hh}, {v}, {t}",
                    "bltu {w}, {er}, 2b",
                    "add {l0}, {l0}, {m}",
                    "sltu {m}, {l0}, {m}",
                    "add {h0}, {h0}, {hh}",
                    "add {h0}, {h0}, {m}",
                    wp = inout(reg) wp,
                    l0 = inout(reg) a[0],
                    h0 = inout(reg) a[1],
                    m = inout(reg) 0u32 => _,
                    hh = inout(reg) 0u32 => _,
                    base = in(reg) cols,
                    mask = in(reg) column_offset_mask(L),
                    er = in(reg) ER_BIT,
                    cs = const column_offset_shift(L),
                    vs = const VALUE_SIGN_SHIFT,
                    w = out(reg) _,
                    t = out(reg) _,
                    v = out(reg) _,
                    options(nostack, readonly),
                );
            }
        }
        2 => {
            // SAFETY: as above; the two lanes of p[col_base + c] are at offsets 0 and 4.
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "addi {wp}, {wp}, 4",
                    "srli {t}, {w}, {cs}",
                    "slli {v}, {w}, {vs}",
                    "and {t}, {t}, {mask}",
                    "srai {v}, {v}, {vs}",
                    "add {t}, {t}, {base}",
                    "lw {p}, 0({t})",
                    "lw {q}, 4({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "mul {n}, {v}, {q}",
                    "add {l0}, {l0}, {m}",
                    "sltu {m}, {l0}, {m}",
                    "mulh {q}, {v}, {q}",
                    "add {h0}, {h0}, {p}",
                    "add {h0}, {h0}, {m}",
                    "add {l1}, {l1}, {n}",
                    "sltu {n}, {l1}, {n}",
                    "add {h1}, {h1}, {q}",
                    "add {h1}, {h1}, {n}",
                    "bltu {w}, {er}, 2b",
                    wp = inout(reg) wp,
                    l0 = inout(reg) a[0],
                    h0 = inout(reg) a[1],
                    l1 = inout(reg) a[2],
                    h1 = inout(reg) a[3],
                    base = in(reg) cols,
                    mask = in(reg) column_offset_mask(L),
                    er = in(reg) ER_BIT,
                    cs = const column_offset_shift(L),
                    vs = const VALUE_SIGN_SHIFT,
                    w = out(reg) _,
                    t = out(reg) _,
                    v = out(reg) _,
                    p = out(reg) _,
                    q = out(reg) _,
                    m = out(reg) _,
                    n = out(reg) _,
                    options(nostack, readonly),
                );
            }
        }
        _ => {
            // SAFETY: as above; the three lanes of p[col_base + c] are at offsets 0, 4, 8.
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "addi {wp}, {wp}, 4",
                    "srli {t}, {w}, {cs}",
                    "slli {v}, {w}, {vs}",
                    "and {t}, {t}, {mask}",
                    "srai {v}, {v}, {vs}",
                    "add {t}, {t}, {base}",
                    "lw {p}, 0({t})",
                    "lw {q}, 4({t})",
                    "lw {r}, 8({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "mul {n}, {v}, {q}",
                    "add {a0}, {a0}, {m}",
                    "sltu {m}, {a0}, {m}",
                    "mulh {q}, {v}, {q}",
                    "add {a1}, {a1}, {p}",
                    "add {a1}, {a1}, {m}",
                    "add {a2}, {a2}, {n}",
                    "sltu {n}, {a2}, {n}",
                    "mul {m}, {v}, {r}",
                    "add {a3}, {a3}, {q}",
                    "add {a3}, {a3}, {n}",
                    "mulh {r}, {v}, {r}",
                    "add {a4}, {a4}, {m}",
                    "sltu {m}, {a4}, {m}",
                    "add {a5}, {a5}, {r}",
                    "add {a5}, {a5}, {m}",
                    "bltu {w}, {er}, 2b",
                    wp = inout(reg) wp,
                    a0 = inout(reg) a[0],
                    a1 = inout(reg) a[1],
                    a2 = inout(reg) a[2],
                    a3 = inout(reg) a[3],
                    a4 = inout(reg) a[4],
                    a5 = inout(reg) a[5],
                    base = in(reg) cols,
                    mask = in(reg) column_offset_mask(L),
                    er = in(reg) ER_BIT,
                    cs = const column_offset_shift(L),
                    vs = const VALUE_SIGN_SHIFT,
                    w = out(reg) _,
                    t = out(reg) _,
                    v = out(reg) _,
                    p = out(reg) _,
                    q = out(reg) _,
                    r = out(reg) _,
                    m = out(reg) _,
                    n = out(reg) _,
                    options(nostack, readonly),
                );
            }
        }
    }
    for (d, acc) in acc.iter_mut().enumerate() {
        *acc = join(a[2 * d], a[2 * d + 1]);
    }
    wp
}

/// [`row`] for one direction with split sums ([`rebuild_split`]), the rows run by
/// [`split_tile1`]: returns the pointer past the row's ER word and the row's split sums (low,
/// coarse); `carried` holds the previous row's last products and takes this row's.
///
/// Software-pipelined as the exact loop is: a trip adds the previous word's two products while
/// its own word is decoded, and the last word's are added after the loop. 13 instructions a
/// word instead of 15, scheduled so that no load or multiply is used within three slots and
/// no shift within two: the word's load (the head) three slots before its decode, p's load
/// three before its `mul`, the value's `srai` two before it.
///
/// Two words a trip, each with its own exit test: the first's a forward `bgeu`, which the
/// VexRiscv predicts not taken and so costs nothing while the row goes on, the second's the
/// backward `bltu`, predicted taken, whose fetch bubble (a clock) is now paid every other
/// word (a Verilator trace measured it at 0.84 clocks a word). The same 13 instructions a
/// word; a row's exit still costs one mispredicted branch, whichever word ends it.
///
/// Every instruction from the row's start is 32 bits (`norvc`) and the start is aligned to 4
/// bytes (`.p2align 2`, padding only where the layout left it at 2 mod 4), so that no 32-bit
/// instruction straddles two fetch words: a trace measured the taken branch to the head at 1
/// clock where the 32-bit instructions after it were aligned, and at 2 where the head (a
/// `c.lw`) sat at 0 mod 4 and put the first `srli` at 2 mod 4. (docs/PERFORMANCE.md, "The
/// whole-K MVU phase, session 16".)
///
/// # Safety
///
/// As [`row`]; the caller allows split sums for the row ([`crate::cg::Plan::split`]).
#[inline(always)]
unsafe fn split_row1<const L: u32>(
    w: *const u32,
    cols: *const u8,
    carried: &mut (u32, u32),
) -> (*const u32, u32, u32) {
    let mut wp = w;
    // The first trip adds the products `carried` (the previous row's last, which its own
    // end added already): the sums start at their negation, so that they are 0 after that
    // add (wrapping, as every add of the split sums), which costs two instructions a row
    // where zeroing the sums and the two products cost four.
    let (mut m, mut hh) = *carried;
    let (low, coarse): (u32, u32);
    // SAFETY: reads only the row's words and p[col_base + c] for its columns.
    unsafe {
        asm!(
            ".p2align 2",
            ".option push",
            ".option norvc",
            "neg {l0}, {m}",
            "neg {c0}, {hh}",
            "2:",
            "lw a4, 0(a5)",
            "addi a5, a5, 4",
            "add {l0}, {l0}, {m}",
            "srli {t}, a4, {cs}",
            "slli {vv}, a4, {vs}",
            "and {t}, {t}, {mask}",
            "add {t}, {t}, {base}",
            "lw {t}, 0({t})",
            "srai {v}, {vv}, {vs}",
            "add {c0}, {c0}, {hh}",
            "mul {m}, {v}, {t}",
            "mulh {hh}, {vv}, {t}",
            "bgeu a4, {er}, 3f",
            "lw a4, 0(a5)",
            "addi a5, a5, 4",
            "add {l0}, {l0}, {m}",
            "srli {t}, a4, {cs}",
            "slli {vv}, a4, {vs}",
            "and {t}, {t}, {mask}",
            "add {t}, {t}, {base}",
            "lw {t}, 0({t})",
            "srai {v}, {vv}, {vs}",
            "add {c0}, {c0}, {hh}",
            "mul {m}, {v}, {t}",
            "mulh {hh}, {vv}, {t}",
            "bltu a4, {er}, 2b",
            "3:",
            "add {l0}, {l0}, {m}",
            "add {c0}, {c0}, {hh}",
            ".option pop",
            inout("a5") wp,
            l0 = out(reg) low,
            c0 = out(reg) coarse,
            m = inout(reg) m,
            hh = inout(reg) hh,
            base = in(reg) cols,
            mask = in(reg) column_offset_mask(L),
            er = in(reg) ER_BIT,
            cs = const column_offset_shift(L),
            vs = const VALUE_SIGN_SHIFT,
            out("a4") _,
            t = out(reg) _,
            v = out(reg) _,
            vv = out(reg) _,
            options(nostack, readonly),
        );
    }
    *carried = (m, hh);
    (wp, low, coarse)
}

/// [`super::run_tile`] for one direction, whole, split sums: [`split_row1`] row after row, the
/// last products of each row carried into the next row's first trip.
///
/// # Safety
///
/// As [`super::run_tile`] with `D` = 1, not `MIRROR`, `SPLIT`.
#[inline(always)]
pub unsafe fn split_tile1<const STORE: bool, const L: u32>(t: &super::TileRun) {
    let stride = super::sum_words_of_shift(L);
    let mut w = t.words;
    let mut y = t.y;
    let cols = t.p_cols as *const u8;
    let mut carried = (0u32, 0u32);
    for _ in 0..t.rows {
        // SAFETY: forwarded from the caller.
        let (next, low, coarse) = unsafe { split_row1::<L>(w, cols, &mut carried) };
        w = next;
        // SAFETY: one row of Kp per tile row, as the caller promised.
        unsafe { super::end_row::<1, STORE>(y, &[rebuild_split(low, coarse)]) };
        y = y.wrapping_add(stride);
    }
}

/// [`row`] for a mirrored tile: each word also multiplies p[n − 1 − col_base − c] into the
/// mirror row's sums.
///
/// # Safety
///
/// As [`row`]; `mirror_cols` points at p[n − 1 − col_base].
#[inline(always)]
pub unsafe fn mirrored_row<const D: usize, const SPLIT: bool, const L: u32>(
    w: *const u32,
    cols: *const u8,
    mirror_cols: *const u8,
    acc: &mut [i64; D],
    mirror_acc: &mut [i64; D],
) -> *const u32 {
    if SPLIT && (D == 1 || D == 3) {
        let mut a = [0u32; 4 * MAX_DIRECTIONS];
        // SAFETY: forwarded; the caller allows split sums for these rows.
        let wp = unsafe { split_mirrored_row::<D, L>(w, cols, mirror_cols, &mut a) };
        for d in 0..D {
            acc[d] = rebuild_split(a[2 * d], a[2 * d + 1]);
            mirror_acc[d] = rebuild_split(a[6 + 2 * d], a[7 + 2 * d]);
        }
        return wp;
    }
    let mut wp = w;
    // Own row's (lo, hi) per direction, then the mirror row's.
    let mut a = [0u32; 4 * MAX_DIRECTIONS];
    match D {
        1 => {
            // SAFETY: reads only the row's words, p[col_base + c] and p[n − 1 − col_base − c].
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "addi {wp}, {wp}, 4",
                    "srli {t}, {w}, {cs}",
                    "slli {v}, {w}, {vs}",
                    "and {t}, {t}, {mask}",
                    "srai {v}, {v}, {vs}",
                    "sub {tm}, {mbase}, {t}",
                    "add {t}, {t}, {base}",
                    "lw {p}, 0({t})",
                    "lw {q}, 0({tm})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "mul {n}, {v}, {q}",
                    "add {l0}, {l0}, {m}",
                    "sltu {m}, {l0}, {m}",
                    "mulh {q}, {v}, {q}",
                    "add {h0}, {h0}, {p}",
                    "add {h0}, {h0}, {m}",
                    "add {l1}, {l1}, {n}",
                    "sltu {n}, {l1}, {n}",
                    "add {h1}, {h1}, {q}",
                    "add {h1}, {h1}, {n}",
                    "bltu {w}, {er}, 2b",
                    wp = inout(reg) wp,
                    l0 = inout(reg) a[0],
                    h0 = inout(reg) a[1],
                    l1 = inout(reg) a[6],
                    h1 = inout(reg) a[7],
                    base = in(reg) cols,
                    mbase = in(reg) mirror_cols,
                    mask = in(reg) column_offset_mask(L),
                    er = in(reg) ER_BIT,
                    cs = const column_offset_shift(L),
                    vs = const VALUE_SIGN_SHIFT,
                    w = out(reg) _,
                    t = out(reg) _,
                    tm = out(reg) _,
                    v = out(reg) _,
                    p = out(reg) _,
                    q = out(reg) _,
                    m = out(reg) _,
                    n = out(reg) _,
                    options(nostack, readonly),
                );
            }
        }
        2 => {
            // SAFETY: as above, two lanes at offsets 0 and 4 of both addresses.
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "addi {wp}, {wp}, 4",
                    "srli {t}, {w}, {cs}",
                    "slli {v}, {w}, {vs}",
                    "and {t}, {t}, {mask}",
                    "srai {v}, {v}, {vs}",
                    "sub {tm}, {mbase}, {t}",
                    "add {t}, {t}, {base}",
                    "lw {p}, 0({t})",
                    "lw {q}, 4({t})",
                    "lw {r}, 0({tm})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "mul {n}, {v}, {q}",
                    "add {a0}, {a0}, {m}",
                    "sltu {m}, {a0}, {m}",
                    "mulh {q}, {v}, {q}",
                    "add {a1}, {a1}, {p}",
                    "add {a1}, {a1}, {m}",
                    "lw {p}, 4({tm})",
                    "add {a2}, {a2}, {n}",
                    "sltu {n}, {a2}, {n}",
                    "mul {m}, {v}, {r}",
                    "add {a3}, {a3}, {q}",
                    "add {a3}, {a3}, {n}",
                    "mulh {r}, {v}, {r}",
                    "mul {n}, {v}, {p}",
                    "add {a6}, {a6}, {m}",
                    "sltu {m}, {a6}, {m}",
                    "mulh {p}, {v}, {p}",
                    "add {a7}, {a7}, {r}",
                    "add {a7}, {a7}, {m}",
                    "add {a8}, {a8}, {n}",
                    "sltu {n}, {a8}, {n}",
                    "add {a9}, {a9}, {p}",
                    "add {a9}, {a9}, {n}",
                    "bltu {w}, {er}, 2b",
                    wp = inout(reg) wp,
                    a0 = inout(reg) a[0],
                    a1 = inout(reg) a[1],
                    a2 = inout(reg) a[2],
                    a3 = inout(reg) a[3],
                    a6 = inout(reg) a[6],
                    a7 = inout(reg) a[7],
                    a8 = inout(reg) a[8],
                    a9 = inout(reg) a[9],
                    base = in(reg) cols,
                    mbase = in(reg) mirror_cols,
                    mask = in(reg) column_offset_mask(L),
                    er = in(reg) ER_BIT,
                    cs = const column_offset_shift(L),
                    vs = const VALUE_SIGN_SHIFT,
                    w = out(reg) _,
                    t = out(reg) _,
                    tm = out(reg) _,
                    v = out(reg) _,
                    p = out(reg) _,
                    q = out(reg) _,
                    r = out(reg) _,
                    m = out(reg) _,
                    n = out(reg) _,
                    options(nostack, readonly),
                );
            }
        }
        _ => {
            // Lanes rotate through three load registers (p, q, r) and two product
            // registers (m, n), so every load has three slots before its multiply and every
            // multiply three before its add; 26 registers, every one the asm may name.
            // SAFETY: as above, three lanes at offsets 0, 4, 8 of both addresses.
            unsafe {
                asm!(
                    "2:",
                    "lw {w}, 0({wp})",
                    "addi {wp}, {wp}, 4",
                    "srli {t}, {w}, {cs}",
                    "slli {v}, {w}, {vs}",
                    "and {t}, {t}, {mask}",
                    "srai {v}, {v}, {vs}",
                    "sub {tm}, {mbase}, {t}",
                    "add {t}, {t}, {base}",
                    "lw {p}, 0({t})",
                    "lw {q}, 4({t})",
                    "lw {r}, 8({t})",
                    "mul {m}, {v}, {p}",
                    "mulh {p}, {v}, {p}",
                    "mul {n}, {v}, {q}",
                    "add {a0}, {a0}, {m}",
                    "sltu {m}, {a0}, {m}",
                    "mulh {q}, {v}, {q}",
                    "add {a1}, {a1}, {p}",
                    "add {a1}, {a1}, {m}",
                    "lw {p}, 0({tm})",
                    "add {a2}, {a2}, {n}",
                    "sltu {n}, {a2}, {n}",
                    "mul {m}, {v}, {r}",
                    "add {a3}, {a3}, {q}",
                    "add {a3}, {a3}, {n}",
                    "mulh {r}, {v}, {r}",
                    "add {a4}, {a4}, {m}",
                    "sltu {m}, {a4}, {m}",
                    "lw {q}, 4({tm})",
                    "mul {n}, {v}, {p}",
                    "add {a5}, {a5}, {r}",
                    "add {a5}, {a5}, {m}",
                    "mulh {p}, {v}, {p}",
                    "add {a6}, {a6}, {n}",
                    "sltu {n}, {a6}, {n}",
                    "lw {r}, 8({tm})",
                    "mul {m}, {v}, {q}",
                    "add {a7}, {a7}, {p}",
                    "add {a7}, {a7}, {n}",
                    "mulh {q}, {v}, {q}",
                    "add {a8}, {a8}, {m}",
                    "sltu {m}, {a8}, {m}",
                    "mul {n}, {v}, {r}",
                    "add {a9}, {a9}, {q}",
                    "add {a9}, {a9}, {m}",
                    "mulh {r}, {v}, {r}",
                    "add {a10}, {a10}, {n}",
                    "sltu {n}, {a10}, {n}",
                    "add {a11}, {a11}, {r}",
                    "add {a11}, {a11}, {n}",
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
                    mask = in(reg) column_offset_mask(L),
                    er = in(reg) ER_BIT,
                    cs = const column_offset_shift(L),
                    vs = const VALUE_SIGN_SHIFT,
                    w = out(reg) _,
                    t = out(reg) _,
                    tm = out(reg) _,
                    v = out(reg) _,
                    p = out(reg) _,
                    q = out(reg) _,
                    r = out(reg) _,
                    m = out(reg) _,
                    n = out(reg) _,
                    options(nostack, readonly),
                );
            }
        }
    }
    for d in 0..D {
        acc[d] = join(a[2 * d], a[2 * d + 1]);
        mirror_acc[d] = join(a[6 + 2 * d], a[7 + 2 * d]);
    }
    wp
}

/// [`mirrored_row`]'s loop as split sums ([`rebuild_split`]) for one or three directions:
/// per direction and row `a[2d]` gets Σ `mul(v, p)` and `a[2d + 1]` Σ `mulh(w << 11, p)`
/// (the own row's, then from `a[6]` the mirror row's). 19 instructions a word for one
/// direction, 39 for three (against 23 and 51 exact). Loads are three slots and more from
/// their multiplies; the adds of the last lane follow their multiplies closer.
///
/// # Safety
///
/// As [`mirrored_row`], and the row within [`super::SPLIT_MAX_WORDS`] and
/// [`super::SPLIT_MAX_ROW_ABS`].
#[inline(always)]
unsafe fn split_mirrored_row<const D: usize, const L: u32>(
    w: *const u32,
    cols: *const u8,
    mirror_cols: *const u8,
    a: &mut [u32; 4 * MAX_DIRECTIONS],
) -> *const u32 {
    let mut wp = w;
    if D == 1 {
        // The word and its pointer are in a4 and a5, so that the loop's head, `lw`, assembles
        // to a 16-bit `c.lw` (its registers must be among x8–x15, and x8 and x9 are not the
        // asm's to name): the VexRiscv fetches aligned 32-bit words, and a taken branch to a
        // 32-bit instruction at an address 2 mod 4 costs a second fetch, a bubble a word
        // (docs/PERFORMANCE.md, "The VexRiscv's stalls, traced"), where the layout put it.
        // SAFETY: reads only the row's words, p[col_base + c] and p[n − 1 − col_base − c].
        unsafe {
            asm!(
                "2:",
                "lw a4, 0(a5)",
                "addi a5, a5, 4",
                "srli {t}, a4, {cs}",
                "slli {vv}, a4, {vs}",
                "and {t}, {t}, {mask}",
                "srai {v}, {vv}, {vs}",
                "sub {tm}, {mbase}, {t}",
                "add {t}, {t}, {base}",
                "lw {p}, 0({t})",
                "lw {q}, 0({tm})",
                "mul {m}, {v}, {p}",
                "mulh {p}, {vv}, {p}",
                "mul {n}, {v}, {q}",
                "mulh {q}, {vv}, {q}",
                "add {l0}, {l0}, {m}",
                "add {c0}, {c0}, {p}",
                "add {l1}, {l1}, {n}",
                "add {c1}, {c1}, {q}",
                "bltu a4, {er}, 2b",
                inout("a5") wp,
                l0 = inout(reg) a[0],
                c0 = inout(reg) a[1],
                l1 = inout(reg) a[6],
                c1 = inout(reg) a[7],
                base = in(reg) cols,
                mbase = in(reg) mirror_cols,
                mask = in(reg) column_offset_mask(L),
                er = in(reg) ER_BIT,
                cs = const column_offset_shift(L),
                vs = const VALUE_SIGN_SHIFT,
                out("a4") _,
                t = out(reg) _,
                tm = out(reg) _,
                v = out(reg) _,
                vv = out(reg) _,
                p = out(reg) _,
                q = out(reg) _,
                m = out(reg) _,
                n = out(reg) _,
                options(nostack, readonly),
            );
        }
    } else {
        // 27 registers: the 12 sums, the word pointer, 4 constants and 10 temporaries.
        // SAFETY: as above, three lanes at offsets 0, 4, 8 of both addresses.
        unsafe {
            asm!(
                "2:",
                "lw {w}, 0({wp})",
                "addi {wp}, {wp}, 4",
                "srli {t}, {w}, {cs}",
                "slli {vv}, {w}, {vs}",
                "and {t}, {t}, {mask}",
                "srai {v}, {vv}, {vs}",
                "sub {tm}, {mbase}, {t}",
                "add {t}, {t}, {base}",
                "lw {p}, 0({t})",
                "lw {q}, 4({t})",
                "lw {r}, 8({t})",
                "mul {m}, {v}, {p}",
                "mulh {p}, {vv}, {p}",
                "mul {n}, {v}, {q}",
                "mulh {q}, {vv}, {q}",
                "add {a0}, {a0}, {m}",
                "add {a1}, {a1}, {p}",
                "mul {m}, {v}, {r}",
                "mulh {r}, {vv}, {r}",
                "add {a2}, {a2}, {n}",
                "add {a3}, {a3}, {q}",
                "lw {p}, 0({tm})",
                "lw {q}, 4({tm})",
                "add {a4}, {a4}, {m}",
                "add {a5}, {a5}, {r}",
                "lw {r}, 8({tm})",
                "mul {m}, {v}, {p}",
                "mulh {p}, {vv}, {p}",
                "mul {n}, {v}, {q}",
                "mulh {q}, {vv}, {q}",
                "add {a6}, {a6}, {m}",
                "add {a7}, {a7}, {p}",
                "mul {m}, {v}, {r}",
                "mulh {r}, {vv}, {r}",
                "add {a8}, {a8}, {n}",
                "add {a9}, {a9}, {q}",
                "add {a10}, {a10}, {m}",
                "add {a11}, {a11}, {r}",
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
                mask = in(reg) column_offset_mask(L),
                er = in(reg) ER_BIT,
                cs = const column_offset_shift(L),
                vs = const VALUE_SIGN_SHIFT,
                w = out(reg) _,
                t = out(reg) _,
                tm = out(reg) _,
                v = out(reg) _,
                vv = out(reg) _,
                p = out(reg) _,
                q = out(reg) _,
                r = out(reg) _,
                m = out(reg) _,
                n = out(reg) _,
                options(nostack, readonly),
            );
        }
    }
    wp
}

/// [`row`]'s three-direction loop as split sums ([`rebuild_split`]): `a[2d]` gets
/// Σ `mul(v, p)` and `a[2d + 1]` Σ `mulh(w << 11, p)`; 23 instructions a word against 29.
///
/// # Safety
///
/// As [`row`], and the row within [`super::SPLIT_MAX_WORDS`] and
/// [`super::SPLIT_MAX_ROW_ABS`].
#[inline(always)]
unsafe fn split_row3(
    w: *const u32,
    cols: *const u8,
    a: &mut [u32; 2 * MAX_DIRECTIONS],
) -> *const u32 {
    let mut wp = w;
    // SAFETY: reads only the row's words and p[col_base + c] (lanes at offsets 0, 4, 8).
    unsafe {
        asm!(
            "2:",
            "lw {w}, 0({wp})",
            "addi {wp}, {wp}, 4",
            "srli {t}, {w}, {cs}",
            "slli {vv}, {w}, {vs}",
            "and {t}, {t}, {mask}",
            "srai {v}, {vv}, {vs}",
            "add {t}, {t}, {base}",
            "lw {p}, 0({t})",
            "lw {q}, 4({t})",
            "lw {r}, 8({t})",
            "mul {m}, {v}, {p}",
            "mulh {p}, {vv}, {p}",
            "mul {n}, {v}, {q}",
            "mulh {q}, {vv}, {q}",
            "add {a0}, {a0}, {m}",
            "add {a1}, {a1}, {p}",
            "mul {m}, {v}, {r}",
            "mulh {r}, {vv}, {r}",
            "add {a2}, {a2}, {n}",
            "add {a3}, {a3}, {q}",
            "add {a4}, {a4}, {m}",
            "add {a5}, {a5}, {r}",
            "bltu {w}, {er}, 2b",
            wp = inout(reg) wp,
            a0 = inout(reg) a[0],
            a1 = inout(reg) a[1],
            a2 = inout(reg) a[2],
            a3 = inout(reg) a[3],
            a4 = inout(reg) a[4],
            a5 = inout(reg) a[5],
            base = in(reg) cols,
            mask = in(reg) COLUMN_OFFSET_MASK,
            er = in(reg) ER_BIT,
            cs = const COLUMN_OFFSET_SHIFT,
            vs = const VALUE_SIGN_SHIFT,
            w = out(reg) _,
            t = out(reg) _,
            v = out(reg) _,
            vv = out(reg) _,
            p = out(reg) _,
            q = out(reg) _,
            r = out(reg) _,
            m = out(reg) _,
            n = out(reg) _,
            options(nostack, readonly),
        );
    }
    wp
}

/// A whole three-direction mirrored tile as split sums, each row's sums rebuilt
/// ([`rebuild_split`]) and stored at its row end inside the loop: the word loop of
/// [`split_mirrored_row`] (39 instructions a word) and 56 a row (the 12 sums zeroed, six
/// rebuilt and stored, the two row pointers stepped), where the compiler's row end around
/// the 27-register loop spilled and reloaded every sum (about 74). The row pointers and
/// the end live in `st`, the one register left over.
///
/// # Safety
///
/// As [`super::run_tile`] with `STORE` and `SPLIT` (`rows` ≥ 1, as validated tiles have).
#[inline(never)]
pub unsafe fn split_mirrored_tile3_store(tile: &super::TileRun) {
    // Kp is 24 bytes a row here: three directions take p's 16-byte lanes ([`super::sum_words`]).
    let y_end = tile.y.wrapping_add(MAX_DIRECTIONS * tile.rows as usize);
    let mut st = [tile.y as usize, tile.y_mirror as usize, y_end as usize];
    // SAFETY: reads the tile's words and p[col_base + c], p[n − 1 − col_base − c]; writes
    // the tile's rows and mirror rows of y (the caller's promise) and `st`.
    unsafe {
        asm!(
            "3:",
            "li {a0}, 0",
            "li {a1}, 0",
            "li {a2}, 0",
            "li {a3}, 0",
            "li {a4}, 0",
            "li {a5}, 0",
            "li {a6}, 0",
            "li {a7}, 0",
            "li {a8}, 0",
            "li {a9}, 0",
            "li {a10}, 0",
            "li {a11}, 0",
            "2:",
            "lw {w}, 0({wp})",
            "addi {wp}, {wp}, 4",
            "srli {t}, {w}, {cs}",
            "slli {vv}, {w}, {vs}",
            "and {t}, {t}, {mask}",
            "srai {v}, {vv}, {vs}",
            "sub {tm}, {mbase}, {t}",
            "add {t}, {t}, {base}",
            "lw {p}, 0({t})",
            "lw {q}, 4({t})",
            "lw {r}, 8({t})",
            "mul {m}, {v}, {p}",
            "mulh {p}, {vv}, {p}",
            "mul {n}, {v}, {q}",
            "mulh {q}, {vv}, {q}",
            "add {a0}, {a0}, {m}",
            "add {a1}, {a1}, {p}",
            "mul {m}, {v}, {r}",
            "mulh {r}, {vv}, {r}",
            "add {a2}, {a2}, {n}",
            "add {a3}, {a3}, {q}",
            "lw {p}, 0({tm})",
            "lw {q}, 4({tm})",
            "add {a4}, {a4}, {m}",
            "add {a5}, {a5}, {r}",
            "lw {r}, 8({tm})",
            "mul {m}, {v}, {p}",
            "mulh {p}, {vv}, {p}",
            "mul {n}, {v}, {q}",
            "mulh {q}, {vv}, {q}",
            "add {a6}, {a6}, {m}",
            "add {a7}, {a7}, {p}",
            "mul {m}, {v}, {r}",
            "mulh {r}, {vv}, {r}",
            "add {a8}, {a8}, {n}",
            "add {a9}, {a9}, {q}",
            "add {a10}, {a10}, {m}",
            "add {a11}, {a11}, {r}",
            "bltu {w}, {er}, 2b",
            // Row end: S = 2^21·coarse + (low − 2^21·coarse mod 2^32), per sum.
            "lw {t}, 0({st})",
            "lw {tm}, 4({st})",
            "slli {p}, {a1}, {ss}",
            "srai {q}, {a1}, {hs}",
            "sltu {p}, {a0}, {p}",
            "add {q}, {q}, {p}",
            "sw {a0}, 0({t})",
            "sw {q}, 4({t})",
            "slli {p}, {a3}, {ss}",
            "srai {q}, {a3}, {hs}",
            "sltu {p}, {a2}, {p}",
            "add {q}, {q}, {p}",
            "sw {a2}, 8({t})",
            "sw {q}, 12({t})",
            "slli {p}, {a5}, {ss}",
            "srai {q}, {a5}, {hs}",
            "sltu {p}, {a4}, {p}",
            "add {q}, {q}, {p}",
            "sw {a4}, 16({t})",
            "sw {q}, 20({t})",
            "slli {p}, {a7}, {ss}",
            "srai {q}, {a7}, {hs}",
            "sltu {p}, {a6}, {p}",
            "add {q}, {q}, {p}",
            "sw {a6}, 0({tm})",
            "sw {q}, 4({tm})",
            "slli {p}, {a9}, {ss}",
            "srai {q}, {a9}, {hs}",
            "sltu {p}, {a8}, {p}",
            "add {q}, {q}, {p}",
            "sw {a8}, 8({tm})",
            "sw {q}, 12({tm})",
            "slli {p}, {a11}, {ss}",
            "srai {q}, {a11}, {hs}",
            "sltu {p}, {a10}, {p}",
            "add {q}, {q}, {p}",
            "sw {a10}, 16({tm})",
            "sw {q}, 20({tm})",
            "addi {t}, {t}, 24",
            "addi {tm}, {tm}, -24",
            "sw {t}, 0({st})",
            "sw {tm}, 4({st})",
            "lw {p}, 8({st})",
            "bne {t}, {p}, 3b",
            wp = inout(reg) tile.words => _,
            st = in(reg) st.as_mut_ptr(),
            base = in(reg) tile.p_cols,
            mbase = in(reg) tile.p_mirror_cols,
            mask = in(reg) COLUMN_OFFSET_MASK,
            er = in(reg) ER_BIT,
            cs = const COLUMN_OFFSET_SHIFT,
            vs = const VALUE_SIGN_SHIFT,
            ss = const super::SPLIT_SHIFT,
            hs = const 32 - super::SPLIT_SHIFT,
            a0 = out(reg) _,
            a1 = out(reg) _,
            a2 = out(reg) _,
            a3 = out(reg) _,
            a4 = out(reg) _,
            a5 = out(reg) _,
            a6 = out(reg) _,
            a7 = out(reg) _,
            a8 = out(reg) _,
            a9 = out(reg) _,
            a10 = out(reg) _,
            a11 = out(reg) _,
            w = out(reg) _,
            t = out(reg) _,
            tm = out(reg) _,
            v = out(reg) _,
            vv = out(reg) _,
            p = out(reg) _,
            q = out(reg) _,
            r = out(reg) _,
            m = out(reg) _,
            n = out(reg) _,
            options(nostack),
        );
    }
}
