//! The MVU inner loop (thesis 4.2.1): one tile's instruction words against the search
//! directions.
//!
//! # Layout it relies on
//!
//! - The search directions of all fused systems are interleaved, `p[i] = [p₀ᵢ, p₁ᵢ, p₂ᵢ, pad]`
//!   ([`Lanes`], 16 bytes), so that one address computed from a word's column serves all three
//!   loads with immediate offsets 0, 4, 8. The byte offset of column c is `16·c`, which is
//!   `(w >> COLUMN_OFFSET_SHIFT) & COLUMN_OFFSET_MASK` of the word `w` (17 and 0x1FF0, derived
//!   from [`deform_shared::word`]'s layout and pinned below): two instructions.
//! - One direction alone has p 4 bytes a node ([`lane_words`]): the offset is `4·c`, the same
//!   two instructions with the shift and mask of lane shift 2 ([`column_offset_shift`],
//!   [`column_offset_mask`]: 19 and 0x7FC), and 512 nodes' p is 2 KiB instead of 8 KiB, half
//!   the VexRiscv's data cache instead of twice it. The loops take the lane shift as a const
//!   generic `L`; where hardware MVUs may run the phase, p stays 16 bytes a node (their
//!   window's layout).
//! - Row sums go to Kp, one `i64` per direction, laid out like p by the direction count
//!   ([`sum_words`]): `[i64; 3]` a row ([`Sums`], 24 bytes) where p is 16 bytes a node, one
//!   `i64` a row where p is 4 bytes a node (one direction without hardware MVUs). 512 rows of
//!   one direction's Kp are then 4 KiB instead of 12, and a row end stores 8 bytes.
//!
//! # Numerics
//!
//! Each product q·p (|q| < 2^20, |p| < 2^30) is exact in `i64`, and so is the row sum (at most
//! 2^12 products of a tile row before the sum could reach 2^62; validated tiles have at most
//! 512 columns per row, and [`crate::cg::plan`] refuses a matrix whose rows could overflow).
//! Nothing is rounded. pᵀKp is formed once per finished row of Kp, exactly
//! ([`p_kp_and_max`]), per row rather than per tile row and mirror row: where every row of K
//! is one row of one tile ([`crate::cg::Plan::fused`]) by each MVU over its own rows right
//! after its tiles, otherwise in the MVU phase's second step.
//!
//! # Loop shape
//!
//! Per word: load it, extract the column byte offset (2 ops) and add the base, sign-extend the
//! value (`slli`/`srai` by [`VALUE_SIGN_SHIFT`] = 11), then per direction one load and an exact 64-bit
//! multiply–accumulate (`mul`, `mulh`, `add`, `sltu`, `add`, `add`), step the word pointer and
//! branch back unless the word has ER (an unsigned compare `w < 2^30` tests ER and EM at
//! once, since a validated tile sets EM only on a word that also has ER). A mirrored tile adds
//! a second address (`p[n−1−col_base] − 16·c`) and a second set of accumulators.
//!
//! Where the plan allows it ([`crate::cg::Plan::split`]: rows of at most 2048 words and
//! Σ|q| below 2^22), the three-direction loops, the one-direction mirrored loop and, where p
//! is 4 bytes a node, the one-direction whole loop keep split sums instead
//! ([`rebuild_split`]): per product `mul`, `mulh` of the word shifted by 11 and two `add`s,
//! the row's exact sum rebuilt at its end; 23 instructions a word instead of 29 (three
//! directions, whole), 19 and 39 instead of 23 and 51 (one and three, mirrored), 13 instead of
//! 15 (one, whole).
#![allow(unsafe_code)]

use deform_shared::protocol::MAX_DIRECTIONS;
use deform_shared::word::{COLUMN_BITS, COLUMN_SHIFT, COLUMN_WINDOW, EM_BIT, ER_BIT, VALUE_BITS};

/// One node's search-direction mantissas of every fused direction, plus padding to 16 bytes.
pub type Lanes = [i32; 4];
/// One row's MVU results, one per direction.
pub type Sums = [i64; MAX_DIRECTIONS];

/// log2 of the bytes of one [`Lanes`]: a column's byte offset in p is c << LANE_SHIFT.
const LANE_SHIFT: u32 = 4;
/// `(w >> COLUMN_OFFSET_SHIFT) & COLUMN_OFFSET_MASK` is the byte offset 16·c of word w's column.
pub const COLUMN_OFFSET_SHIFT: u32 = column_offset_shift(LANE_SHIFT);
/// See [`COLUMN_OFFSET_SHIFT`]: the column field, moved down to bit `LANE_SHIFT` (4: 16-byte lanes).
pub const COLUMN_OFFSET_MASK: u32 = column_offset_mask(LANE_SHIFT);

/// [`COLUMN_OFFSET_SHIFT`] for p laid out `1 << lane_shift` bytes a node.
pub const fn column_offset_shift(lane_shift: u32) -> u32 {
    COLUMN_SHIFT - lane_shift
}

/// [`COLUMN_OFFSET_MASK`] for p laid out `1 << lane_shift` bytes a node.
pub const fn column_offset_mask(lane_shift: u32) -> u32 {
    (COLUMN_WINDOW - 1) << lane_shift
}

/// i32 words a node of p takes in the MVU phase's software layout for `directions` fused
/// directions: 1 for one direction, else 4 (a whole [`Lanes`]).
///
/// One direction uses one lane of the four, so the 16-byte layout made p four times the bytes
/// it needs: 8 KiB for 512 nodes, twice the VexRiscv's 4 KiB data cache, whose misses on p
/// were a third of the MVU phase's stalls (docs/PERFORMANCE.md, "The VexRiscv's stalls,
/// traced"). The hardware MVUs' p window stays 16 bytes a node: the solver uses this layout
/// only where no [`crate::mvu_backend::MvuBackend`] lends it the window.
pub const fn lane_words(directions: usize) -> usize {
    if directions == 1 {
        1
    } else {
        4
    }
}

/// log2 of the bytes a node of p takes with `lane_words` i32 words a node (1 or 4).
pub const fn lane_shift(lane_words: usize) -> u32 {
    2 + lane_words.trailing_zeros()
}

/// i64 words a row of Kp takes where p is `lane_words` i32 words a node: 1 where p is one lane
/// (one direction, [`lane_words`]), else [`MAX_DIRECTIONS`] (a whole [`Sums`]).
///
/// Kp follows p's layout for the same reason: 24 bytes a row made one direction's Kp 12 KiB
/// for 512 rows, three times the VexRiscv's 4 KiB data cache, through which every row end
/// stores and pᵀKp and pass R read it back. The hardware MVUs' Kp window stays 24 bytes a row:
/// where an [`crate::mvu_backend::MvuBackend`] exists p is 16 bytes a node, so Kp is too.
pub const fn sum_words(lane_words: usize) -> usize {
    if lane_words == 1 {
        1
    } else {
        MAX_DIRECTIONS
    }
}

/// [`sum_words`] for p laid out `1 << lane_shift` bytes a node.
pub const fn sum_words_of_shift(lane_shift: u32) -> usize {
    sum_words(1 << (lane_shift - 2))
}

/// `kp`'s first `rows` rows laid out `R` i64 words a row ([`sum_words`]): the same buffer,
/// n [`Sums`] long, seen with the solve's stride (its first `R·rows` words).
///
/// # Panics
///
/// If `R` is 0 or the rows do not fit in `kp`.
pub fn sum_rows<const R: usize>(kp: &mut [Sums], rows: usize) -> &mut [[i64; R]] {
    let flat = kp.as_flattened_mut();
    assert!(R > 0 && rows * R <= flat.len());
    // SAFETY: [i64; R] has the alignment of i64 and no padding; the rows lie within `flat`,
    // which this borrow holds exclusively.
    unsafe { core::slice::from_raw_parts_mut(flat.as_mut_ptr().cast(), rows) }
}
/// `((w << VALUE_SIGN_SHIFT) as i32) >> VALUE_SIGN_SHIFT` is word w's value, sign-extended.
pub const VALUE_SIGN_SHIFT: u32 = 32 - VALUE_BITS;

/// Split sums ([`rebuild_split`]): the weight of a row's coarse sum, 2^21. The loops form
/// `mulh(w << VALUE_SIGN_SHIFT, p)` = ⌊v·p / 2^21⌋, the word shifted as it is for its value.
pub const SPLIT_SHIFT: u32 = 32 - VALUE_SIGN_SHIFT;
/// Split sums are exact for a tile row of at most this many words (its coarse sum is below the
/// exact one by less than one unit, 2^21, per word: less than 2^32 in all).
pub const SPLIT_MAX_WORDS: u64 = 1 << (32 - SPLIT_SHIFT);
/// … and Σ|q| over the row (raw units) at most this: with |p| ≤ 2^30 the coarse sum then stays
/// inside `i32` (|⌊S / 2^21⌋| ≤ Σ|q|·2^9 + words < 2^31).
pub const SPLIT_MAX_ROW_ABS: u64 = (1 << (31 - 30 + SPLIT_SHIFT)) - SPLIT_MAX_WORDS;

/// A row's exact sum S from its split sums: `low` = S mod 2^32 (the `mul` words summed, wrapping)
/// and `coarse` = Σ ⌊v·p / 2^21⌋ (the `mulh` words of the shifted value, wrapping). The coarse
/// sum times 2^21 is below S by e ∈ [0, 2^32) (less than 2^21 per word, [`SPLIT_MAX_WORDS`]
/// words) and is exact as an `i32` ([`SPLIT_MAX_ROW_ABS`]), so S = 2^21·coarse + e, where e is
/// `low` − 2^21·coarse mod 2^32: S's low word is `low`, its high word that of 2^21·coarse plus
/// the carry of adding e. Each product then costs `mul`, `mulh` and two `add`s instead of the
/// exact 64-bit sum's `mul`, `mulh` and four (`add`, `sltu`, `add`, `add`).
#[inline(always)]
pub fn rebuild_split(low: u32, coarse: u32) -> i64 {
    let t = coarse << SPLIT_SHIFT;
    let high = (((coarse as i32) >> (32 - SPLIT_SHIFT)) as u32).wrapping_add(u32::from(low < t));
    ((u64::from(high) << 32) | u64::from(low)) as i64
}

// The loops below rely on this layout: 16-byte lanes, the column field right above the value
// field, ER right above the column field and EM above ER (so `w < ER_BIT` means "neither").
// The assembly takes the shifts as `const` operands; these pin them to the values the
// disassembly in docs/PERFORMANCE.md shows.
const _: () = assert!(1 << LANE_SHIFT == core::mem::size_of::<Lanes>());
const _: () = assert!(COLUMN_SHIFT == VALUE_BITS);
const _: () = assert!(ER_BIT == 1 << (COLUMN_SHIFT + COLUMN_BITS) && EM_BIT == ER_BIT << 1);
const _: () = assert!(COLUMN_OFFSET_SHIFT == 17 && COLUMN_OFFSET_MASK == 0x1FF0);
const _: () = assert!(column_offset_shift(lane_shift(1)) == 19);
const _: () = assert!(column_offset_mask(lane_shift(1)) == 0x7FC);
const _: () = assert!(lane_shift(lane_words(3)) == LANE_SHIFT);
const _: () = assert!(sum_words_of_shift(lane_shift(1)) == 1);
const _: () = assert!(sum_words_of_shift(LANE_SHIFT) == MAX_DIRECTIONS);
const _: () = assert!(VALUE_SIGN_SHIFT == 11);

/// Where one tile's words read and write. All pointers are into the solver's buffers.
#[derive(Clone, Copy)]
pub struct TileRun {
    /// The tile's first word.
    pub words: *const u32,
    /// Rows in the tile (ER words to go).
    pub rows: u32,
    /// `&p[col_base]`: column c of the tile reads `p[col_base + c]` (p laid out as the
    /// kernel's `L` or [`run_tile_dyn`]'s `lane_words` says: only an address, of a node's
    /// first lane, so not a [`Lanes`] where p is 4 bytes a node).
    pub p_cols: *const Lanes,
    /// `&p[n − 1 − col_base]`: a mirrored word reads `p[n − 1 − col_base − c]`.
    pub p_mirror_cols: *const Lanes,
    /// Where row `row_base`'s sums go (its first direction's); the next row's are one row of
    /// Kp further ([`sum_words`] of the kernel's `L`: 1 or 3 words).
    pub y: *mut i64,
    /// Where the mirror row `n − 1 − row_base`'s sums go; the next tile row's mirror is one
    /// row *lower*.
    pub y_mirror: *mut i64,
}

/// pᵀKp over rows `p`/`kp` (finished rows) for `directions`, exactly, and the OR of |Kp| per
/// direction (whose highest bit is that of max |Kp|). p is `S` lanes a node ([`lane_words`]),
/// Kp `R` sums a row ([`sum_words`]).
///
/// Each product p·Kp (|p| < 2^30, |Kp| < 2^62) is split by Kp's 32-bit halves h (signed) and l
/// (unsigned) into p·l and p·h, two 64-bit products; their words are summed in three `i64`s by
/// weight 2^0, 2^32 and 2^64, which cannot overflow for any n ≤ 2^16 (below 2^48, 2^50 and
/// 2^46), and are joined into the `i128` once. That is about half the instructions of an
/// `i128` accumulation per row on rv32; one direction at a time keeps the six words of the
/// sums in registers.
pub fn p_kp_and_max<const S: usize, const R: usize>(
    p: &[[i32; S]],
    kp: &[[i64; R]],
    directions: usize,
) -> ([i128; MAX_DIRECTIONS], [u64; MAX_DIRECTIONS]) {
    let mut p_kp = [0i128; MAX_DIRECTIONS];
    let mut or = [0u64; MAX_DIRECTIONS];
    for d in 0..directions.min(MAX_DIRECTIONS).min(S).min(R) {
        let (mut w0, mut w1, mut w2) = (0i64, 0i64, 0i64);
        let mut o = 0u64;
        for (pi, ki) in p.iter().zip(kp) {
            let (pd, v) = (pi[d] as i64, ki[d]);
            let low = pd * (v as u32 as i64);
            let high = pd * (v >> 32);
            w0 += low as u32 as i64;
            w1 += (low >> 32) + (high as u32 as i64);
            w2 += high >> 32;
            o |= (v ^ (v >> 63)) as u64;
        }
        p_kp[d] = i128::from(w0) + (i128::from(w1) << 32) + (i128::from(w2) << 64);
        or[d] = o;
    }
    (p_kp, or)
}

/// Rows [`p_kp_bounded`] takes at once: below 2^13, so that pᵀKp over them stays below 2^95.
pub const P_KP_BOUNDED_ROWS: usize = (1 << 13) - 1;

/// [`p_kp_and_max`] for rows whose |Kp| is below 2^52 (every row of a matrix the plan allows
/// split sums for, [`crate::cg::Plan::split`]: |Kp| ≤ Σ|q|·2^30 < 2^52) and |p| ≤ 2^30, at most
/// [`P_KP_BOUNDED_ROWS`] rows: the same results, with about five instructions fewer per row and
/// direction.
///
/// The four 32-bit words of p·lo (lo unsigned) and p·hi are summed in 32-bit words: the
/// lowest with its carries counted apart, the signed high word of p·lo offset by 2^31 (an
/// `xor`) so that it is summed unsigned, with its carries and those of p·hi's low word into
/// the top word, which takes p·hi's high word and simply wraps: |pᵀKp| < 2^13·2^30·2^52 =
/// 2^95, so the sum modulo 2^96, less the offsets, sign-extended from bit 95, is exact.
pub fn p_kp_bounded<const S: usize, const R: usize>(
    p: &[[i32; S]],
    kp: &[[i64; R]],
    directions: usize,
) -> ([i128; MAX_DIRECTIONS], [u64; MAX_DIRECTIONS]) {
    let mut p_kp = [0i128; MAX_DIRECTIONS];
    let mut or = [0u64; MAX_DIRECTIONS];
    let rows = p.len().min(kp.len());
    for d in 0..directions.min(MAX_DIRECTIONS).min(S).min(R) {
        let (mut x0, mut k1, mut y1, mut y2) = (0u32, 0u32, 0u32, 0u32);
        let (mut o0, mut o1) = (0u32, 0u32);
        for (pi, ki) in p.iter().zip(kp) {
            let (pd, v) = (i64::from(pi[d]), ki[d]);
            let (lo, hi) = (v as u32, (v >> 32) as i32);
            let low = pd * i64::from(lo);
            let high = pd * i64::from(hi);
            let a = low as u32;
            let b = ((low >> 32) as u32) ^ (1 << 31);
            let (c, top) = (high as u32, (high >> 32) as u32);
            x0 = x0.wrapping_add(a);
            k1 = k1.wrapping_add(u32::from(x0 < a));
            y1 = y1.wrapping_add(b);
            let c1 = u32::from(y1 < b);
            y1 = y1.wrapping_add(c);
            let c2 = u32::from(y1 < c);
            y2 = y2.wrapping_add(top).wrapping_add(c1).wrapping_add(c2);
            let sign = (hi >> 31) as u32;
            o0 |= lo ^ sign;
            o1 |= (hi as u32) ^ sign;
        }
        let sum = u128::from(x0)
            .wrapping_add((u128::from(y1) + u128::from(k1)) << 32)
            .wrapping_add(u128::from(y2) << 64)
            .wrapping_sub((rows as u128) << 63);
        p_kp[d] = ((sum << 32) as i128) >> 32;
        or[d] = (u64::from(o1) << 32) | u64::from(o0);
    }
    (p_kp, or)
}

/// Runs one tile for `D` fused directions (`MIRROR`: persymmetric half storage), each row sum
/// *stored* into `y` (and each mirror row's into `y_mirror`) if `STORE`, else *added*.
///
/// A row's sum may be stored where it is the only one the row gets ([`crate::cg::Plan::fused`]:
/// every row of K is one row of one tile, own or mirror, and the MVUs do not overlap); then
/// nothing zeroes the rows first and no second step adds partial rows up. Otherwise rows were
/// zeroed and take their tiles' sums by adding.
///
/// # Safety
///
/// - The tile passed [`deform_shared::matrix::validate_tile`] for dimension n: `rows` ER words,
///   the last one ends the tile, every column c has `col_base + c < n`.
/// - `p_cols` is `&p[col_base]` of a `p` with at least n elements of `1 << L` bytes (`4·D`
///   of them lanes); for `MIRROR`, `p_mirror_cols` is `&p[n − 1 − col_base]`.
/// - `y` points at `rows` writable rows of Kp, each [`sum_words_of_shift`]`(L)` i64 words
///   (and `y_mirror` at the top of `rows` rows going down, for `MIRROR`) that no one else
///   accesses during the call.
///
/// `SPLIT` (the firmware's three-direction loops and one-direction mirrored loop; others
/// ignore it) sums each row as split sums ([`rebuild_split`]), which the caller allows only
/// for rows within [`SPLIT_MAX_WORDS`] and [`SPLIT_MAX_ROW_ABS`] ([`crate::cg::Plan::split`]);
/// the sums are the same bits.
#[inline(always)]
pub unsafe fn run_tile<
    const D: usize,
    const MIRROR: bool,
    const STORE: bool,
    const SPLIT: bool,
    const L: u32,
>(
    t: &TileRun,
) {
    const { assert!(4 * D <= 1 << L && L <= LANE_SHIFT && D <= sum_words_of_shift(L)) };
    let stride = sum_words_of_shift(L);
    #[cfg(target_arch = "riscv32")]
    if D == 3 && MIRROR && STORE && SPLIT {
        // SAFETY: forwarded; the whole tile, row ends included, in one loop.
        unsafe { riscv::split_mirrored_tile3_store(t) };
        return;
    }
    #[cfg(target_arch = "riscv32")]
    if D == 1 && !MIRROR && SPLIT {
        // SAFETY: forwarded; the row loop with each row's last products carried.
        unsafe { riscv::split_tile1::<STORE, L>(t) };
        return;
    }
    let mut w = t.words;
    let mut y = t.y;
    let mut y_mirror = t.y_mirror;
    let cols = t.p_cols as *const u8;
    let mirror_cols = t.p_mirror_cols as *const u8;
    for _ in 0..t.rows {
        let mut acc = [0i64; D];
        let mut mirror_acc = [0i64; D];
        #[cfg(target_arch = "riscv32")]
        {
            // SAFETY: as for `portable_row`, whose sums these compute exactly.
            w = unsafe {
                if MIRROR {
                    riscv::mirrored_row::<D, SPLIT, L>(
                        w,
                        cols,
                        mirror_cols,
                        &mut acc,
                        &mut mirror_acc,
                    )
                } else {
                    riscv::row::<D, SPLIT, L>(w, cols, &mut acc)
                }
            };
        }
        #[cfg(not(target_arch = "riscv32"))]
        {
            // SAFETY: forwarded from the caller.
            w = unsafe {
                portable_row::<D, MIRROR, L>(w, cols, mirror_cols, &mut acc, &mut mirror_acc)
            };
        }
        // SAFETY: one slot per tile row, as the caller promised.
        unsafe { end_row::<D, STORE>(y, &acc) };
        y = y.wrapping_add(stride);
        if MIRROR {
            // SAFETY: as above, walking down from the mirror of row_base.
            unsafe { end_row::<D, STORE>(y_mirror, &mirror_acc) };
            y_mirror = y_mirror.wrapping_sub(stride);
        }
    }
}

/// A row's end: its sum `acc` stored into the row at `y` (`STORE`) or added to it.
///
/// # Safety
///
/// `y` is a writable row of at least `D` sums no one else accesses.
#[inline(always)]
unsafe fn end_row<const D: usize, const STORE: bool>(y: *mut i64, acc: &[i64; D]) {
    // SAFETY: forwarded from the caller.
    let out = unsafe { &mut *y.cast::<[i64; D]>() };
    for d in 0..D {
        if STORE {
            out[d] = acc[d];
        } else {
            out[d] += acc[d];
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
#[cfg_attr(target_arch = "riscv32", allow(dead_code))] // the specification; the firmware runs `riscv`
unsafe fn portable_row<const D: usize, const MIRROR: bool, const L: u32>(
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
        let offset = ((word >> column_offset_shift(L)) & column_offset_mask(L)) as usize;
        let value = (((word << VALUE_SIGN_SHIFT) as i32) >> VALUE_SIGN_SHIFT) as i64;
        // SAFETY: offset = c << L with col_base + c < n, so these are p[col_base + c]'s D
        // lanes.
        let lanes = unsafe { &*(cols.wrapping_add(offset) as *const [i32; D]) };
        for d in 0..D {
            acc[d] += value * lanes[d] as i64;
        }
        if MIRROR {
            // SAFETY: n − 1 − col_base − c ≥ 0, so these are p[n − 1 − col_base − c]'s.
            let mirrored = unsafe { &*(mirror_cols.wrapping_sub(offset) as *const [i32; D]) };
            for d in 0..D {
                mirror_acc[d] += value * mirrored[d] as i64;
            }
        }
        if word >= ER_BIT {
            return w;
        }
    }
}

/// [`run_tile`] for a run-time direction count (1..=3), mirror flag, row end and split sums
/// (used by the three-direction loops and the one-direction loops, the whole one only where p is
/// 4 bytes a node: the two-direction loops keep their exact sums, and so does the one-direction
/// whole loop on 16-byte lanes), p
/// laid out `S` i32 words a node: 1 (one direction, [`lane_words`]) or 4. `S` is a constant so
/// that each layout's dispatch costs what the one layout's did.
///
/// # Safety
///
/// As [`run_tile`]; `split` only where [`run_tile`] allows `SPLIT`; `S` is 1 only for one
/// direction.
#[inline(never)]
pub unsafe fn run_tile_dyn<const S: usize>(
    t: &TileRun,
    directions: usize,
    mirrored: bool,
    store: bool,
    split: bool,
) {
    const { assert!(S == 1 || S == size_of::<Lanes>() / 4) };
    // SAFETY: forwarded contract.
    unsafe {
        if S == 1 {
            debug_assert!(directions == 1);
            run_tile_compact(t, mirrored, store, split);
        } else {
            run_tile_lanes(t, directions, mirrored, store, split);
        }
    }
}

/// [`run_tile_dyn`] for one direction with p 4 bytes a node.
///
/// # Safety
///
/// As [`run_tile_dyn`].
#[inline(always)]
unsafe fn run_tile_compact(t: &TileRun, mirrored: bool, store: bool, split: bool) {
    const L: u32 = lane_shift(1);
    // SAFETY: forwarded contract.
    unsafe {
        match (mirrored, store, split) {
            (true, false, true) => run_tile::<1, true, false, true, L>(t),
            (true, true, true) => run_tile::<1, true, true, true, L>(t),
            (false, false, true) => run_tile::<1, false, false, true, L>(t),
            (false, true, true) => run_tile::<1, false, true, true, L>(t),
            (false, false, _) => run_tile::<1, false, false, false, L>(t),
            (true, false, _) => run_tile::<1, true, false, false, L>(t),
            (false, true, _) => run_tile::<1, false, true, false, L>(t),
            (true, true, _) => run_tile::<1, true, true, false, L>(t),
        }
    }
}

/// [`run_tile_dyn`] with p 16 bytes a node (a whole [`Lanes`]).
///
/// # Safety
///
/// As [`run_tile_dyn`].
#[inline(always)]
unsafe fn run_tile_lanes(t: &TileRun, directions: usize, mirrored: bool, store: bool, split: bool) {
    const L: u32 = LANE_SHIFT;
    // SAFETY: forwarded contract.
    unsafe {
        match (directions, mirrored, store, split) {
            (1, true, false, true) => run_tile::<1, true, false, true, L>(t),
            (1, true, true, true) => run_tile::<1, true, true, true, L>(t),
            (3, true, false, true) => run_tile::<3, true, false, true, L>(t),
            (3, true, true, true) => run_tile::<3, true, true, true, L>(t),
            (3, false, false, true) => run_tile::<3, false, false, true, L>(t),
            (3, false, true, true) => run_tile::<3, false, true, true, L>(t),
            (1, false, false, _) => run_tile::<1, false, false, false, L>(t),
            (2, false, false, _) => run_tile::<2, false, false, false, L>(t),
            (1, true, false, _) => run_tile::<1, true, false, false, L>(t),
            (2, true, false, _) => run_tile::<2, true, false, false, L>(t),
            (_, false, false, _) => run_tile::<3, false, false, false, L>(t),
            (_, true, false, _) => run_tile::<3, true, false, false, L>(t),
            (1, false, true, _) => run_tile::<1, false, true, false, L>(t),
            (2, false, true, _) => run_tile::<2, false, true, false, L>(t),
            (1, true, true, _) => run_tile::<1, true, true, false, L>(t),
            (2, true, true, _) => run_tile::<2, true, true, false, L>(t),
            (_, false, true, _) => run_tile::<3, false, true, false, L>(t),
            (_, true, true, _) => run_tile::<3, true, true, false, L>(t),
        }
    }
}

/// The inner loop in RV32IM assembly, for one, two and three directions, whole and mirrored
/// tiles: 15 instructions per word for one direction, 22 for two (11 per multiply–accumulate),
/// 29 for three (9.67); mirrored tiles 23, 37 and 51 (11.5, 9.25 and 8.5 per
/// multiply–accumulate, each word serving its row and the mirror row). Rust's code generation
/// spills the accumulator words of the fused loops and adds a longer address computation; this
/// is the loop the thesis's MVU pipeline does in hardware. The portable loop ([`portable_row`])
/// is the specification, and the HIL tests check that the firmware's results equal the host's
/// bit for bit.
///
/// # Scheduling
///
/// The loops are ordered for an in-order five-stage core such as VexRiscv, where a result used
/// too soon stalls the pipeline: a load's or a multiply's within three slots of its use, a
/// shift's within two (the project's VexRiscv notes: CPI 1.64 naive, about 1.15 scheduled).
/// The two shifts that decode the column and the value are interleaved, the lanes' loads (own
/// and mirror, where registers allow) are issued before the first multiply, and lanes rotate
/// through load and product registers so each multiply is three slots from its load and each
/// add three from its multiply. What no order within one word can hide is the word's own load
/// before its decode (one slot short in every loop) and, where only one or two lanes follow,
/// a lane's load before its multiply. The one-direction whole-K loop, with no other work to
/// fill those slots, is software-pipelined: a trip adds the previous word's product while it
/// decodes its own, and the last product is added after the loop (6 instructions more per row,
/// none per word). Otherwise the instruction counts are those of the unscheduled loops, so
/// QEMU's counts do not change.
///
/// One loop is unrolled, the one-direction whole loop on split sums (two words a trip): every
/// word may end its row, so each keeps its exit test, but the first word's is a forward branch,
/// free on VexRiscv while not taken, where a taken backward branch costs a fetch bubble
/// (docs/PERFORMANCE.md, "The whole-K MVU phase, session 16"; an earlier unrolled trial
/// measured no gain, issue 13). The others are not: their bodies are long enough that the
/// bubble is a small part of a word.
///
/// The six loops (one, two and three directions, whole and mirrored) are written out rather
/// than generated by a macro: the schedule above interleaves each variant's loads, multiplies
/// and carries differently, so a template would either fix one schedule for all or need as
/// many cases as there are loops.
#[cfg(target_arch = "riscv32")]
mod riscv;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn p_kp_is_the_exact_sum_of_products() {
        let big = (1i64 << 62) - 1;
        let values = [
            0i64,
            1,
            -1,
            big,
            -big,
            0x1234_5678_9ABC,
            -(1 << 40) + 7,
            u32::MAX as i64,
        ];
        let ps = [0i32, 1, -1, (1 << 30) - 1, -(1 << 30) + 1, 12345];
        let mut p = Vec::new();
        let mut kp = Vec::new();
        for (i, &v) in values.iter().enumerate() {
            for (j, &q) in ps.iter().enumerate() {
                p.push([q, ps[(j + i) % ps.len()], -q, 0]);
                kp.push([v, -v, values[(i + j) % values.len()]]);
            }
        }
        let (got, or) = p_kp_and_max(&p, &kp, 3);
        for d in 0..3 {
            let want: i128 = p
                .iter()
                .zip(&kp)
                .map(|(a, b)| a[d] as i128 * b[d] as i128)
                .sum();
            assert_eq!(got[d], want, "direction {d}");
            let max = kp.iter().map(|r| r[d].unsigned_abs()).max().unwrap();
            assert_eq!(64 - or[d].leading_zeros(), 64 - max.leading_zeros());
        }
    }

    /// Kp's buffer seen one sum a row: row i is word i of the buffer (the first rows' words),
    /// three a row: the rows themselves; too many rows panic.
    #[test]
    fn sum_rows_lay_kp_out_by_its_stride() {
        let mut kp: Vec<Sums> = (0..4).map(|i| [10 * i, 10 * i + 1, 10 * i + 2]).collect();
        let one: Vec<i64> = sum_rows::<1>(&mut kp, 12).iter().map(|r| r[0]).collect();
        assert_eq!(one, [0, 1, 2, 10, 11, 12, 20, 21, 22, 30, 31, 32]);
        sum_rows::<1>(&mut kp, 4)[3][0] = -1;
        assert_eq!(kp[1], [-1, 11, 12]);
        assert_eq!(sum_rows::<3>(&mut kp, 4)[2], [20, 21, 22]);
        let over = std::panic::catch_unwind(move || sum_rows::<3>(&mut kp, 5).len());
        assert!(over.is_err());
    }

    /// Split sums of `terms` (value, p) as the firmware's loops form them: `mul(v, p)` and
    /// `mulh(v << 11, p)` summed with wrapping, then [`rebuild_split`].
    fn split_sum(terms: &[(i32, i32)]) -> i64 {
        let (mut low, mut coarse) = (0u32, 0u32);
        for &(v, p) in terms {
            low = low.wrapping_add(v.wrapping_mul(p) as u32);
            let shifted = (v << VALUE_SIGN_SHIFT) as i64;
            coarse = coarse.wrapping_add(((shifted * p as i64) >> 32) as u32);
        }
        rebuild_split(low, coarse)
    }

    fn exact_sum(terms: &[(i32, i32)]) -> i64 {
        terms.iter().map(|&(v, p)| v as i64 * p as i64).sum()
    }

    /// At the limits the plan allows: the longest rows, the largest Σ|q| at either sign, the
    /// largest |p| and values, and random rows within them.
    #[test]
    fn split_sums_are_exact_within_the_plans_limits() {
        let words = SPLIT_MAX_WORDS as usize;
        let row_abs = SPLIT_MAX_ROW_ABS as i64;
        let p_max = (1i32 << 30) - 1;
        let v_max = (1i32 << 20) - 1;
        let mut cases: Vec<Vec<(i32, i32)>> = Vec::new();
        for sign in [1, -1] {
            // Σ|q| at its limit in few large words, the rest of the row ±1 (every floor below).
            let mut row = Vec::new();
            let mut left = row_abs - (words as i64 - 4);
            while left > 0 {
                let v = left.min(v_max as i64) as i32;
                row.push((sign * v, p_max));
                left -= v as i64;
            }
            while row.len() < words {
                row.push((1, -sign * 3));
            }
            cases.push(row);
            // Every word's floor as far below as it goes: products ≡ −1 mod 2^21.
            cases.push(vec![(sign, sign * ((1 << 21) - 1)); words]);
            cases.push(vec![(sign, -sign); words]);
            cases.push(vec![(-sign * ((1 << 20) - 1), -(1 << 21) - 1); 3]);
        }
        let mut rng = crate::test_rng::Rng(0x5EED_0005_9117);
        for _ in 0..200 {
            let len = 1 + rng.below(words as u64) as usize;
            let mut budget = row_abs;
            let row: Vec<(i32, i32)> = (0..len)
                .map(|_| {
                    let cap = budget.min(v_max as i64).max(0) as u64;
                    let v = rng.below(cap + 1) as i64;
                    budget -= v;
                    let v = if rng.next() & 1 == 0 { v } else { -v } as i32;
                    let p = (rng.below(2 * p_max as u64 + 1) as i64 - p_max as i64) as i32;
                    (v, p)
                })
                .collect();
            cases.push(row);
        }
        for (i, row) in cases.iter().enumerate() {
            assert!(row.len() <= words);
            assert!(row.iter().map(|&(v, _)| (v as i64).abs()).sum::<i64>() <= row_abs);
            assert_eq!(split_sum(row), exact_sum(row), "case {i}");
        }
    }

    /// The limits are tight where they must be: one word more, or a Σ|q| far enough over, and
    /// the split sum is wrong.
    #[test]
    fn split_sums_fail_beyond_their_limits() {
        let words = SPLIT_MAX_WORDS as usize;
        // Each floor 2^21 − 1 below: 2^11 + 1 words put the error past 2^32.
        let long = vec![(1, (1 << 21) - 1); words + 1];
        assert_ne!(split_sum(&long), exact_sum(&long));
        // A coarse sum past 2^31: Σ|q| = 2^22 + 2^12 at |p| just below 2^30.
        let big = vec![((1 << 20) - 1, (1 << 30) - 1); 5];
        assert_ne!(split_sum(&big), exact_sum(&big));
    }

    /// The bounded pᵀKp equals the general one at its limits: |Kp| up to 2^52 − 1 at either
    /// sign, |p| up to 2^30, the most rows, and random rows within them.
    #[test]
    fn bounded_p_kp_equals_the_general_one() {
        let mut rng = crate::test_rng::Rng(0xB0D1_0057_0001);
        let k_max = (1i64 << 52) - 1;
        let p_max = 1i32 << 30;
        let mut cases: Vec<(Vec<Lanes>, Vec<Sums>)> = Vec::new();
        let rows = P_KP_BOUNDED_ROWS;
        for (ps, ks) in [
            (p_max, k_max),
            (-p_max, k_max),
            (p_max, -k_max),
            (-p_max, -k_max),
        ] {
            cases.push((vec![[ps, -ps, ps, 0]; rows], vec![[ks, ks, -ks]; rows]));
        }
        // Low words at their largest, high words at zero and −1, zeros.
        let edges = [
            0i64,
            1,
            -1,
            u32::MAX as i64,
            -(u32::MAX as i64),
            1 << 32,
            k_max,
            -k_max,
        ];
        let (mut p, mut kp) = (Vec::new(), Vec::new());
        for i in 0..rows {
            let q = [p_max, -p_max, 0, 1, -1, p_max - 1][i % 6];
            p.push([q, -q, q / 3, 0]);
            let v = edges[i % edges.len()];
            kp.push([v, edges[(i / 7) % edges.len()], -v]);
        }
        cases.push((p, kp));
        for _ in 0..20 {
            let len = rng.below(rows as u64 + 1) as usize;
            let draw_p = |rng: &mut crate::test_rng::Rng| {
                (rng.below(2 * p_max as u64 + 1) as i64 - p_max as i64) as i32
            };
            let draw_k = |rng: &mut crate::test_rng::Rng| {
                let bits = rng.below(53);
                let k = (rng.next() >> (64 - bits.max(1))) as i64;
                if rng.next() & 1 == 0 {
                    k
                } else {
                    -k
                }
            };
            let p: Vec<Lanes> = (0..len)
                .map(|_| [draw_p(&mut rng), draw_p(&mut rng), draw_p(&mut rng), 0])
                .collect();
            let kp: Vec<Sums> = (0..len)
                .map(|_| [draw_k(&mut rng), draw_k(&mut rng), draw_k(&mut rng)])
                .collect();
            cases.push((p, kp));
        }
        // Twice the rows at the largest products: the sum passes 2^95 and the result is wrong.
        let over = 2 * rows;
        let (p, kp) = (vec![[p_max; 4]; over], vec![[k_max; 3]; over]);
        assert_ne!(p_kp_bounded(&p, &kp, 1).0, p_kp_and_max(&p, &kp, 1).0);
        for (i, (p, kp)) in cases.iter().enumerate() {
            assert!(kp.iter().flatten().all(|v| v.unsigned_abs() < 1 << 52));
            for directions in [1, 3] {
                assert_eq!(
                    p_kp_bounded(p, kp, directions),
                    p_kp_and_max(p, kp, directions),
                    "case {i}, {directions} direction(s)"
                );
            }
            // One direction's p 4 bytes a node (`lane_words(1)`) and its Kp 8 bytes a row
            // (`sum_words(1)`): the same first sums.
            let compact: Vec<[i32; 1]> = p.iter().map(|l| [l[0]]).collect();
            let compact_kp: Vec<[i64; 1]> = kp.iter().map(|k| [k[0]]).collect();
            let want = p_kp_and_max(p, kp, 1);
            assert_eq!(p_kp_bounded(&compact, kp, 1), want, "case {i}, compact");
            assert_eq!(p_kp_and_max(&compact, kp, 1), want, "case {i}, compact");
            let got = p_kp_bounded(&compact, &compact_kp, 1);
            assert_eq!(got, want, "case {i}, compact Kp");
            let got = p_kp_and_max(&compact, &compact_kp, 1);
            assert_eq!(got, want, "case {i}, compact Kp");
        }
    }
}
