//! The harts' exact partial results, added up by the harts themselves in the parallel phase.
//!
//! Every parallel phase ends with per-hart integers — pᵀKp (`i128`), Σr² (`u128`) and ORs of
//! magnitudes — that hart 0 needs as totals. Looping over eight harts' 128-bit values with
//! their carries cost hart 0 about 24 instructions per hart, field and direction on the serial
//! path between the phases (docs/PERFORMANCE.md, "Hart 0's scalar planning, session 5"). Here
//! each hart adds its own value into shared accumulators at the end of its share, where the
//! harts overlap, and hart 0 only reads the totals.
//!
//! A 128-bit value is added as five limbs of [`LIMB_BITS`] bits, one 32-bit word each: the
//! three bits above a limb leave room for the carries of [`MAX_HARTS`] limbs, so no word
//! carries into the next, and integer addition in any order gives the same total (the harts
//! race to the words): the wrapping sum of the `u128`s, i.e. the exact `i128` or `u128` sum the
//! serial loop formed. [`Wide::take`] propagates the carries once and packs the words.
//!
//! Read-modify-write is a compare-and-swap loop: LLVM lowers `compare_exchange_weak` to LR/SC,
//! whereas `fetch_add` and `fetch_or` become `amoadd.w` and `amoor.w`, which the LiteX
//! VexRiscv does not implement (see the firmware's `atomic` module). `Relaxed` suffices: the
//! executor's end-of-phase barrier orders every hart's additions before hart 0's reads.

use core::sync::atomic::{AtomicU32, Ordering::Relaxed};

use deform_shared::protocol::{MAX_DIRECTIONS, MAX_HARTS};

use crate::svu::HartOut;

/// Bits of a 128-bit value per limb: 29, so that [`MAX_HARTS`] limbs below 2^29 sum below 2^32.
pub const LIMB_BITS: u32 = 29;
const _: () = assert!((MAX_HARTS as u64) << LIMB_BITS <= 1 << 32);
/// Limbs of a 128-bit value: ⌈128 / 29⌉.
const LIMBS: usize = 128_usize.div_ceil(LIMB_BITS as usize);
const LIMB_MASK: u32 = (1 << LIMB_BITS) - 1;

/// `a += v` (wrapping) as a compare-and-swap loop: see the module's note on AMOs.
#[inline(always)]
fn add(a: &AtomicU32, v: u32) {
    let mut current = a.load(Relaxed);
    while let Err(now) = a.compare_exchange_weak(current, current.wrapping_add(v), Relaxed, Relaxed)
    {
        current = now;
    }
}

/// `a |= v` as a compare-and-swap loop; nothing to do for 0.
#[inline(always)]
fn or(a: &AtomicU32, v: u32) {
    if v == 0 {
        return;
    }
    let mut current = a.load(Relaxed);
    while let Err(now) = a.compare_exchange_weak(current, current | v, Relaxed, Relaxed) {
        current = now;
    }
}

/// A 128-bit sum of up to [`MAX_HARTS`] values, added limb by limb.
#[derive(Default)]
pub struct Wide([AtomicU32; LIMBS]);

impl Wide {
    /// Adds `v` (an `i128` as its two's-complement `u128`). A zero limb is skipped: Σr² and a
    /// non-negative pᵀKp leave the top limbs zero.
    #[inline(always)]
    pub fn add(&self, v: u128) {
        for (k, limb) in self.0.iter().enumerate() {
            let part = (v >> (k as u32 * LIMB_BITS)) as u32 & LIMB_MASK;
            if part != 0 {
                add(limb, part);
            }
        }
    }

    /// The sum of every value added since the last take, wrapped to 128 bits, and zero again.
    /// Only while no hart adds.
    #[inline(always)]
    pub fn take(&self) -> u128 {
        let mut words = [0u32; LIMBS];
        for (w, limb) in words.iter_mut().zip(&self.0) {
            *w = limb.load(Relaxed);
            limb.store(0, Relaxed);
        }
        pack(words)
    }
}

/// Σ words[k]·2^(29k) mod 2^128, each word at most 8·(2^29 − 1) = 2^32 − 8: the carries moved up limb by limb
/// (a word plus the carry below stays below 2^32), then the 29-bit limbs packed into a `u128`.
#[inline(always)]
fn pack(mut words: [u32; LIMBS]) -> u128 {
    for k in 0..LIMBS - 1 {
        words[k + 1] += words[k] >> LIMB_BITS;
        words[k] &= LIMB_MASK;
    }
    words.iter().enumerate().fold(0u128, |v, (k, &w)| {
        v | u128::from(w) << (k as u32 * LIMB_BITS)
    })
}

/// An OR of 32-bit values.
#[derive(Default)]
pub struct Or(AtomicU32);

impl Or {
    #[inline(always)]
    pub fn add(&self, v: u32) {
        or(&self.0, v);
    }

    /// The OR of every value added since the last take, and zero again. Only while no hart adds.
    #[inline(always)]
    pub fn take(&self) -> u32 {
        let v = self.0.load(Relaxed);
        self.0.store(0, Relaxed);
        v
    }
}

/// An OR of 64-bit values, as two words.
#[derive(Default)]
pub struct Or64([Or; 2]);

impl Or64 {
    #[inline(always)]
    pub fn add(&self, v: u64) {
        self.0[0].add(v as u32);
        self.0[1].add((v >> 32) as u32);
    }

    #[inline(always)]
    pub fn take(&self) -> u64 {
        u64::from(self.0[0].take()) | u64::from(self.0[1].take()) << 32
    }
}

/// The shared accumulators of every field of [`crate::svu::HartOut`], per direction. All zero
/// between phases: each phase's results are taken (read and cleared) on hart 0 after it.
#[derive(Default)]
pub struct Totals {
    pub p_kp: [Wide; MAX_DIRECTIONS],
    pub kp_or: [Or64; MAX_DIRECTIONS],
    pub rr: [Wide; MAX_DIRECTIONS],
    pub r_or: [Or; MAX_DIRECTIONS],
    pub x_or: [Or; MAX_DIRECTIONS],
    pub p_or: [Or; MAX_DIRECTIONS],
    pub b_or: [Or; MAX_DIRECTIONS],
    pub x_any: [Or; MAX_DIRECTIONS],
}

impl Totals {
    /// pᵀKp and the OR of |Kp| of direction d into `out`.
    #[inline(always)]
    pub fn take_mvu(&self, out: &mut HartOut, d: usize) {
        out.p_kp[d] = self.p_kp[d].take() as i128;
        out.kp_or[d] = self.kp_or[d].take();
    }

    /// Σr² and the OR of r²'s high words of direction d into `out` (pass R).
    #[inline(always)]
    pub fn take_r(&self, out: &mut HartOut, d: usize) {
        out.rr[d] = self.rr[d].take();
        out.r_or[d] = self.r_or[d].take();
    }

    /// The ORs of x and p of direction d into `out` (pass XP).
    #[inline(always)]
    pub fn take_xp(&self, out: &mut HartOut, d: usize) {
        out.x_or[d] = self.x_or[d].take();
        out.p_or[d] = self.p_or[d].take();
    }

    /// The set-up's Σb² and ORs of direction d into `out`.
    pub fn take_setup(&self, out: &mut HartOut, d: usize) {
        out.rr[d] = self.rr[d].take();
        out.b_or[d] = self.b_or[d].take();
        out.x_or[d] = self.x_or[d].take();
        out.x_any[d] = self.x_any[d].take();
    }
}

/// Where a hart's results of a phase go: with one hart, straight into the totals' slot (its
/// results are the totals, and adding limbs would only cost it); with several, into the shared
/// [`Totals`], which hart 0 takes into the slot after the phase.
pub enum Sink<'a> {
    Slot(&'a mut HartOut),
    Shared(&'a Totals),
}

impl Sink<'_> {
    #[inline(always)]
    pub fn p_kp(&mut self, d: usize, v: i128) {
        match self {
            Sink::Slot(out) => out.p_kp[d] = v,
            Sink::Shared(t) => t.p_kp[d].add(v as u128),
        }
    }

    #[inline(always)]
    pub fn kp_or(&mut self, d: usize, v: u64) {
        match self {
            Sink::Slot(out) => out.kp_or[d] = v,
            Sink::Shared(t) => t.kp_or[d].add(v),
        }
    }

    #[inline(always)]
    pub fn rr(&mut self, d: usize, v: u128) {
        match self {
            Sink::Slot(out) => out.rr[d] = v,
            Sink::Shared(t) => t.rr[d].add(v),
        }
    }

    /// One of the OR fields (`r_or`, `x_or`, `p_or`, `b_or`, `x_any`), chosen by `field`.
    #[inline(always)]
    pub fn or(&mut self, field: OrField, d: usize, v: u32) {
        match self {
            Sink::Slot(out) => field.of_slot(out)[d] = v,
            Sink::Shared(t) => field.of_totals(t)[d].add(v),
        }
    }
}

/// The 32-bit OR fields of [`HartOut`] and [`Totals`].
#[derive(Debug, Clone, Copy)]
pub enum OrField {
    R,
    X,
    P,
    B,
    XAny,
}

impl OrField {
    #[inline(always)]
    fn of_slot(self, out: &mut HartOut) -> &mut [u32; MAX_DIRECTIONS] {
        match self {
            OrField::R => &mut out.r_or,
            OrField::X => &mut out.x_or,
            OrField::P => &mut out.p_or,
            OrField::B => &mut out.b_or,
            OrField::XAny => &mut out.x_any,
        }
    }

    #[inline(always)]
    fn of_totals(self, t: &Totals) -> &[Or; MAX_DIRECTIONS] {
        match self {
            OrField::R => &t.r_or,
            OrField::X => &t.x_or,
            OrField::P => &t.p_or,
            OrField::B => &t.b_or,
            OrField::XAny => &t.x_any,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values at the edges of 128 bits and of every limb, and random ones of every width.
    fn values() -> Vec<u128> {
        let mut v = vec![0, 1, u128::MAX, i128::MIN as u128, i128::MAX as u128];
        for s in 0..128 {
            let p = 1u128 << s;
            v.extend([p, p - 1, p.wrapping_neg(), (p - 1).wrapping_neg(), !p]);
        }
        let mut rng = fastrand::Rng::with_seed(19);
        for _ in 0..20_000 {
            let bits = rng.u32(0..=128);
            let x = rng.u128(..);
            v.push(if bits == 128 {
                x
            } else {
                x & ((1u128 << bits) - 1)
            });
        }
        v
    }

    #[test]
    fn wide_sums_equal_the_serial_wrapping_sum_for_every_hart_count() {
        let values = values();
        let mut rng = fastrand::Rng::with_seed(5);
        let wide = Wide::default();
        for round in 0..values.len() {
            let harts = 1 + round % MAX_HARTS;
            let mut serial = 0u128;
            for _ in 0..harts {
                let v = values[rng.usize(..values.len())];
                serial = serial.wrapping_add(v);
                wide.add(v);
            }
            assert_eq!(wide.take(), serial, "round {round}");
        }
        assert_eq!(wide.take(), 0, "take clears the sum");
    }

    #[test]
    fn signed_sums_come_back_exact() {
        let cases: [&[i128]; 4] = [
            &[-1, 1],
            &[i128::MIN / 8; 8],
            &[i128::MAX / 8; 8],
            &[
                -5,
                -(1 << 100),
                1 << 100,
                3,
                -(1 << 87),
                7,
                i128::MIN / 4,
                2,
            ],
        ];
        let wide = Wide::default();
        for parts in cases {
            parts.iter().for_each(|&v| wide.add(v as u128));
            assert_eq!(wide.take() as i128, parts.iter().sum::<i128>());
        }
    }

    #[test]
    fn the_largest_limbs_of_eight_harts_carry_through_every_word() {
        let wide = Wide::default();
        for _ in 0..MAX_HARTS {
            wide.add(u128::MAX);
        }
        assert_eq!(wide.take(), u128::MAX.wrapping_mul(MAX_HARTS as u128));
    }

    #[test]
    fn ors_equal_the_serial_or() {
        let values = values();
        let (or32, or64) = (Or::default(), Or64::default());
        for chunk in values.chunks(MAX_HARTS) {
            let (mut s32, mut s64) = (0u32, 0u64);
            for &v in chunk {
                (s32, s64) = (s32 | v as u32, s64 | (v >> 40) as u64);
                or32.add(v as u32);
                or64.add((v >> 40) as u64);
            }
            assert_eq!((or32.take(), or64.take()), (s32, s64));
        }
    }
}
