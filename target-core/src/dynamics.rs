//! Target-resident dynamic frames ([`deform_shared::dynamics`], protocol version 12): the
//! target's half. The tool set and the state's bookkeeping, and the integer passes of a
//! backward-Euler step S·v₁ = M·v₀ − h·K·u₀ (tool velocities moved over), u₁ = u₀ + h·v₁. The
//! session (`dynamic_glue.rs`) owns the vectors and runs the passes on its harts:
//!
//! 1. K·u₀: one MVU pass over the resident copy of K ([`crate::cg::product`]), each row sum
//!    exact in `i64`.
//! 2. **Pass B** ([`rhs_share`]): b₁ = m·v₀ − h·K·u₀ per row as two SVU terms rounded to nearest
//!    ([`RhsPlan`]), and the change d = b₁ − b₀ exactly (`i64`, into K·u₀'s slot, read no
//!    more). Hart 0 then writes the tool's rows: b₁ᵢ −= S_it·v₁t on the rows coupled to a tool
//!    node, b₁t = S_tt·v₁t on its own row, with d there.
//! 3. The start's residual for v₁ ≈ v₀ (u₁ ≈ u₀ + h·v₀): r₀ = b₁ − S·v₀ = d + (b₀ − S·v₀), the
//!    previous step's final residual r plus d, by the SVU's pass R (r ← 1·d + r). O(n) instead
//!    of an MVU pass; the solve starts from it and checks its end against b − S·v as always
//!    (also where r₀ is already within the tolerance: it is an estimate).
//! 4. The solve S·v₁ = b₁ from v₀, then **pass U** ([`advance_share`]): u₁ = u₀ + h·v₁ as an
//!    SVU update (h·v₁ rounded, u₀ shifted), the tool nodes set to their prescribed values.
//!
//! The force the tool exerts at node t is M·(v₁ − v₀)/h + C·v₁ + K·u₁ summed over the tool:
//! with S = M + h·C + h²·K that is ((S·v₁)_t − m·v₀t)/h + (K·u₀)_t, from the tool rows of S and K
//! on hart 0.

use deform_shared::dynamics::{DynamicError, DynamicParams, DynamicTool};
use deform_shared::live::{LiveError, MAX_TOOL_NODES};
use deform_shared::word::{VALUE_MAX, VALUE_MIN};
use heapless::Vec;

use crate::predict::{scale, scale_low, scale_low_wide};
use crate::svu::{
    magnitude_bits, magnitude_bound, normalising_shift, sum_squares, term, Block, Lin, Narrow,
    Scalar, Term,
};
use crate::upper::{Lower, Upper};

/// A dynamic session's tool set as it arrives, then the stepping state.
#[derive(Default)]
pub struct Dynamic {
    tools: Vec<DynamicTool, MAX_TOOL_NODES>,
    /// Per tool, Σ|q| over its row of S and over its row of K (raw values, exact as `u64`,
    /// converted once): pass B's plan bounds the tool's part of b with them every step.
    magnitudes: Vec<[f64; 2], MAX_TOOL_NODES>,
    started: Option<Stepping>,
}

/// The state of a started dynamic session besides the vectors: u is the session's solution (in
/// x, exponent with it), v is in x0, r in r, b in b.
#[derive(Debug, Clone, Copy)]
pub struct Stepping {
    pub params: DynamicParams,
    /// Per direction, v's block.
    pub v: [Block; 3],
    /// Per direction, a bound on max |u| (u's exponent is the session's solution exponent).
    pub u_bound: [u64; 3],
    /// Per direction, r's block where r is b − S·v for the current b and v, checked at the end
    /// of the last solve; `None` where it is not (no solve yet, or one that ran out of budget).
    pub residual: [Option<Block>; 3],
    /// Per direction, a rigorous bound on ‖r − (b − S·v)‖₂ (real units) of `residual`'s r
    /// ([`crate::cg::Outcome::drift`]): a step starts from r in O(n) and may accept its
    /// solve's recursive residual without the exact pass only where this is finite.
    pub drift: [Upper; 3],
    /// Per direction, a rigorous bound on ‖ε − ε₋₁‖₂, where ε is `residual`'s r minus
    /// b − S·v (bounded by `drift`) and ε₋₁ the same of the residual the history keeps
    /// (r₋₁f, [`History::r1_drift`]). The extrapolated start's error is 2ε − ε₋₁ plus its
    /// own roundings, which is at most ‖ε‖ + ‖ε − ε₋₁‖ + theirs: across a run of steps that
    /// skip their closing pass this grows by each step's own roundings, where 2‖ε‖ + ‖ε₋₁‖
    /// roughly doubles at every step ([`start_drift`]).
    pub delta: [Upper; 3],
    /// Per direction, the steps since r was last formed by an exact pass: at
    /// [`MAX_UNCHECKED`] the next step's solve checks its residual whatever the bound says.
    pub unchecked: [u32; 3],
    /// The tool's displacements at the current state, in the order of the `DynamicTool`s.
    pub tool_u: [[f32; 3]; MAX_TOOL_NODES],
    /// Per direction, the OR of |K·u₀| of this step's MVU pass (0 where u is at rest).
    pub ku_or: [u64; 3],
    /// Per direction, what the extrapolated start of the next step needs, where the session's
    /// spare storage holds it ([`History`]).
    pub history: [Option<History>; 3],
    /// The exponent of the current step's field frames (`ReadField`), fixed at its first chunk
    /// so that every chunk of a step's field shares it; cleared by each step.
    pub field_exponent: Option<i8>,
    /// Frames since `DynamicStart` (a measuring build's phase choice, `dynamic_glue.rs`).
    pub frames: u32,
}

/// The last step's velocity change Δv₀ = v₀ − v₋₁, right-hand side change d₀ = b₀ − b₋₁ and
/// the residual r₋₁f its solve started from, kept so that the next step starts from
/// v₀ + Δv₀ (u₁ ≈ u₀ + h·(2v₀ − v₋₁)) with its residual in O(n) ([`residual_share`]). Their
/// blocks; the mantissas are in the session's spare storage.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct History {
    pub dv: Block,
    pub d0: Block,
    pub r1: Block,
    /// A bound on max |d₀ − (b₀ − b₋₁)| (real units): d₁'s own rounding and its narrowing.
    pub d0_err: Upper,
    /// r₋₁f's drift ([`Stepping::drift`] when it was r₀f).
    pub r1_drift: Upper,
}

/// At most this many steps in a row accept their residual on the drift's bound alone; the
/// next checks it by an exact pass (as live frames re-anchor theirs, [`crate::superpose`]).
pub const MAX_UNCHECKED: u32 = 8;

/// A rigorous bound on ‖r₀ − (b₁ − S·x₀)‖₂ (real units) for pass D's start residual
/// ([`residual_share`]), `root_n` ≥ √n for n elements, ‖S‖∞ = `s_inf`:
///
/// - from v₀ (`extrapolated` `None`): r₀ = d₁ + r₀f, so r₀f's drift `e0`, d₁'s rounding
///   (below one unit of its exponent `e_d` per element, [`RhsPlan::change`]) and pass D's two
///   rounded shifts (½ unit of r₀'s exponent `e` each);
/// - from v₀ + Δv₀ (`Some((history, e_x, a_halves))`, x₀'s exponent after pass A `e_x` and
///   the bound of its rounding in halves of those units, [`crate::cg::update_error`]): r₀ = d₁ + 2·r₀f
///   − d₀ − r₋₁f, which holds exactly for the exact quantities (S·v₀ = b₀ − ρ₀, S·Δv₀ = d₀ −
///   ρ₀ + ρ₋₁); each stored one's error adds: r₀f's twice, r₋₁f's, d₁'s, d₀'s, pass D's four
///   rounded shifts, and S times x₀'s errors — Δv's two rounded terms (one unit of its
///   exponent) and pass A's update (`a_units` of x₀'s exponent),
///   each row of S times max |δx| at most ‖S‖∞ max |δx|.
///
/// Kept in integers, rounded up ([`Upper`]): hart 0 forms it every step.
pub fn start_drift(
    root_n: Upper,
    s_inf: Upper,
    exponents: (i32, i32),
    e0: Upper,
    extrapolated: Option<(&History, i32, u64)>,
) -> Upper {
    let local = start_local(root_n, s_inf, exponents, extrapolated);
    match extrapolated {
        None => e0.plus(local),
        Some((h, _, _)) => e0.scale2(1).plus(h.r1_drift).plus(local),
    }
}

/// The part of [`start_drift`] that the start's own roundings add (the carried drifts left
/// out): √n times d₁'s rounding and pass D's shifts, and extrapolating also d₀'s and ‖S‖∞
/// times x₀'s errors. The extrapolated start's error is 2ε₀ − ε₋₁ plus this much, so with a
/// bound D on ‖ε₀ − ε₋₁‖ ([`Stepping::delta`]) it is also at most e₀ + D + this.
pub fn start_local(
    root_n: Upper,
    s_inf: Upper,
    (e_d, e): (i32, i32),
    extrapolated: Option<(&History, i32, u64)>,
) -> Upper {
    let d1 = Upper::small(1, e_d);
    match extrapolated {
        None => root_n.times(d1.plus(Upper::small(1, e))),
        Some((h, e_x, a_halves)) => {
            let x_err = Upper::small(1, h.dv.e).plus(Upper::small(a_halves, e_x - 1));
            let per_element = d1
                .plus(h.d0_err)
                .plus(Upper::small(2, e))
                .plus(s_inf.times(x_err));
            root_n.times(per_element)
        }
    }
}

impl Stepping {
    /// The history direction `d`'s next start extrapolates from (v₀ + Δv₀), if it does, for a
    /// right-hand side of Σb² = `bb` at exponent `e_b`: only from a bounded residual; after a
    /// step that skipped its closing pass always; right after an exact pass only where the
    /// drift the extrapolated start carries, e₀ + `delta` (or e₀ + r₋₁f's), is at most
    /// 2^−`EXTRAPOLATE_MARGIN`/2 of tol·‖b‖. Otherwise the start is v₀, whose residual
    /// d₁ + r₀f carries e₀ alone: right after an exact pass that is the pass's rounding,
    /// while r₋₁f's may be a whole run of skipped steps' drift, which would keep the next
    /// steps from skipping (measured on the needle: `hil-sim/examples/dynamic_drift.rs`).
    /// The start from v₀ costs the needle a second iteration, about what the closing pass
    /// costs, and lets the runs of skips that follow start from a small drift. A choice of
    /// start only: either start's bound is rigorous.
    pub fn start_history(&self, d: usize, (bb, e_b): (u128, i32)) -> Option<History> {
        self.residual[d]?;
        let h = self.history[d]?;
        if self.unchecked[d] != 0 {
            return Some(h);
        }
        // Right after an exact pass only (soft-f64 and `Lower` work on hart 0's serial path).
        let e0 = self.drift[d];
        let delta = if self.delta[d].is_finite() {
            self.delta[d]
        } else {
            e0.plus(h.r1_drift)
        };
        let carried = e0.plus(delta);
        let tol = Lower::from_f64(f64::from(self.params.tolerance));
        let t2 = tol.times(tol).times(Lower::wide(bb, 2 * e_b));
        carried
            .times(carried)
            .scale2(EXTRAPOLATE_MARGIN)
            .at_most(t2)
            .then_some(h)
    }
}

/// [`Stepping::start_history`]'s margin: a start extrapolates where its carried drift is at
/// most 2^−m/2 of tol·‖b‖ after an exact pass. Measured on the needle (in process, the
/// portable loops): 0 gives the old behaviour (always extrapolate; 137 of 299 steps skip
/// in one iteration), 2 gives 157, 4 and above 192 with the `delta` bound (171 without).
pub const EXTRAPOLATE_MARGIN: i32 = 4;

impl Dynamic {
    /// Forgets everything (a new matrix, a `Hello`, a live session).
    pub fn clear(&mut self) {
        *self = Dynamic::default();
    }

    pub fn tools(&self) -> &[DynamicTool] {
        &self.tools
    }

    /// Per tool, Σ|q| over its rows of S and K, in the order of [`Dynamic::tools`].
    pub fn row_magnitudes(&self) -> &[[f64; 2]] {
        &self.magnitudes
    }

    pub fn state(&self) -> Option<&Stepping> {
        self.started.as_ref()
    }

    /// The tool set and the stepping state, borrowed together.
    pub fn parts(&mut self) -> Result<(&[DynamicTool], &mut Stepping), DynamicError> {
        let Dynamic { tools, started, .. } = self;
        Ok((tools, started.as_mut().ok_or(DynamicError::NotStarted)?))
    }

    /// Adds a tool node of an n-node matrix. A tool after `DynamicStart` begins a new set.
    pub fn add_tool(&mut self, tool: DynamicTool, n: u32) -> Result<(), LiveDynamicError> {
        if self.started.take().is_some() {
            self.tools.clear();
            self.magnitudes.clear();
        }
        let node = Self::check_tool(&tool, n)?;
        if self.tools.iter().any(|t| t.s.node == node) {
            return Err(LiveError::DuplicateNode { node }.into());
        }
        let magnitudes = [row_magnitude(&tool.s), row_magnitude(&tool.k)];
        self.tools.push(tool).map_err(|_| {
            LiveDynamicError::from(LiveError::TooManyNodes {
                max: MAX_TOOL_NODES as u8,
            })
        })?;
        // As many slots as tools: this push cannot fail where the tool's did not.
        let _ = self.magnitudes.push(magnitudes);
        Ok(())
    }

    /// A tool's faults, or its node: S's and K's rows name the same node and columns, all
    /// within the matrix, every value within the 21-bit value field.
    fn check_tool(tool: &DynamicTool, n: u32) -> Result<u32, LiveDynamicError> {
        let (s, k) = (&tool.s, &tool.k);
        let same_columns = s.row.len() == k.row.len()
            && s.row.iter().zip(&k.row).all(|(a, b)| a.column == b.column);
        if s.node != k.node || !same_columns {
            return Err(DynamicError::RowsDiffer.into());
        }
        if s.node >= n {
            return Err(LiveError::NodeOutOfRange { node: s.node }.into());
        }
        if let Some(c) = s.row.iter().find(|c| c.column >= n) {
            return Err(LiveError::ColumnOutOfRange { column: c.column }.into());
        }
        let fits = |v: i32| (VALUE_MIN..=VALUE_MAX).contains(&v);
        let values = [s, k]
            .into_iter()
            .flat_map(|r| core::iter::once(r.diagonal).chain(r.row.iter().map(|c| c.value)));
        if !values.into_iter().all(fits) {
            return Err(LiveError::ValueOutOfRange.into());
        }
        Ok(s.node)
    }

    /// Starts the session at rest with the tools given so far.
    pub fn start(&mut self, params: DynamicParams) -> Result<&mut Stepping, LiveDynamicError> {
        if self.tools.is_empty() {
            return Err(LiveError::NoTool.into());
        }
        let positive = |v: f32| v.is_finite() && v > 0.0;
        if !(positive(params.h) && positive(params.mass) && positive(params.tolerance)) {
            return Err(DynamicError::BadParams.into());
        }
        Ok(self.started.insert(Stepping {
            params,
            v: [Block::ZERO; 3],
            u_bound: [0; 3],
            residual: [None; 3],
            drift: [Upper::INFINITE; 3],
            delta: [Upper::INFINITE; 3],
            unchecked: [0; 3],
            tool_u: [[0.0; 3]; MAX_TOOL_NODES],
            ku_or: [0; 3],
            history: [None; 3],
            field_exponent: None,
            frames: 0,
        }))
    }
}

/// A refusal of a dynamic request: a tool-set fault shared with the live loop, or a dynamic
/// one.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LiveDynamicError {
    Live(LiveError),
    Dynamic(DynamicError),
}

impl From<LiveError> for LiveDynamicError {
    fn from(e: LiveError) -> Self {
        LiveDynamicError::Live(e)
    }
}

impl From<DynamicError> for LiveDynamicError {
    fn from(e: DynamicError) -> Self {
        LiveDynamicError::Dynamic(e)
    }
}

/// How pass B forms b₁ = m·v₀ − h·K·u₀ and d = b₁ − b₀ in one direction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RhsPlan {
    /// m·v₀ into b₁'s exponent.
    pub mass: Term,
    /// −h·K·u₀, K·u₀ narrowed to 31 bits first.
    pub narrow: Narrow,
    pub stiffness: Term,
    /// b₁'s exponent.
    pub e: i32,
    /// d's exponent, and the left shifts of b₁ and b₀ onto it (b₀'s may be negative: a
    /// rounded right shift).
    pub e_d: i32,
    pub shift_new: i32,
    pub shift_old: i32,
}

impl RhsPlan {
    /// The plan for mass `m`, time step `h`, v₀'s block `v`, K·u₀'s OR of magnitudes `ku_or`
    /// at exponent `e_ku`, the largest tool contribution `tool` (a bound, real units, on
    /// |S_it·v₁t| summed over the tools at any row) and b₀'s exponent `e_old`. Counts a
    /// multiplier that does not fit in `sat`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        m: f64,
        h: f64,
        v: Block,
        ku_or: u64,
        e_ku: i32,
        tool: f64,
        e_old: i32,
        sat: &mut u32,
    ) -> RhsPlan {
        let (narrow, e_offset, bound) = Narrow::new(crate::svu::bound_of_u64(ku_or), sat);
        let ku = Block {
            e: e_ku + e_offset,
            bound,
        };
        let (mass, minus_h) = (Scalar::of_f64(m), Scalar::of_f64(-h));
        let unit = Block { e: 0, bound: 1 };
        let parts = [
            magnitude_bound(mass, v),
            magnitude_bound(minus_h, ku),
            magnitude_bound(Scalar::of_f64(tool), unit),
        ];
        let e = crate::superpose::exponent_for(&parts).unwrap_or(e_old);
        // d = b₁ − b₀ exactly where both exponents are within 31 bits of the larger one.
        let e_d = e.max(e_old) - 31;
        RhsPlan {
            mass: term(mass, v, normalising_shift(v.bound), e, sat),
            narrow,
            stiffness: term(minus_h, ku, 0, e, sat),
            e,
            e_d,
            shift_new: e - e_d,
            shift_old: e_old - e_d,
        }
    }

    /// b₁ at its exponent from v₀ and K·u₀.
    #[inline(always)]
    fn element(&self, v: i32, ku: i64) -> i32 {
        let k = self.narrow.apply(ku);
        self.mass
            .apply_rounded(v)
            .wrapping_add(self.stiffness.apply_rounded(k))
    }

    /// d = b₁ − b₀ at d's exponent: exact unless b₀'s exponent is below it.
    #[inline(always)]
    pub fn change(&self, new: i32, old: i32) -> i64 {
        (i64::from(new) << self.shift_new) - scale(i64::from(old), -self.shift_old)
    }
}

/// What a hart's share of pass B measured.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RhsSums {
    /// Σb₁² (exact) and the OR of |b₁|.
    pub bb: u128,
    pub b_or: u32,
    /// The OR of |d|.
    pub d_or: u64,
}

/// Pass B on one share: b (holding b₀) becomes b₁ from v₀ and K·u₀ (lane `lane` of `kp`, `R`
/// sums a row as [`crate::cg::product`] laid it out), whose slot then holds d = b₁ − b₀.
pub fn rhs_share<const R: usize>(
    b: &mut [i32],
    kp: &mut [[i64; R]],
    v: &[i32],
    lane: usize,
    plan: &RhsPlan,
) -> RhsSums {
    let mut out = RhsSums::default();
    for ((bi, ki), &vi) in b.iter_mut().zip(kp.iter_mut()).zip(v) {
        let new = plan.element(vi, ki[lane]);
        let d = plan.change(new, *bi);
        *bi = new;
        ki[lane] = d;
        out.b_or |= magnitude_bits(new);
        out.d_or |= (d ^ (d >> 63)) as u64;
    }
    out.bb = sum_squares(b);
    out
}

/// Pass U on one share: u ← `lin`(v) + u (h·v₁ rounded, u₀ shifted), and, where the step
/// keeps a history, the step's velocity change Δv = v₁ − v₀ (v₀ from `v0`) by `dv` into
/// `dv_out`. Returns the ORs of |u| and |Δv|.
pub fn advance_share(
    u: &mut [i32],
    v: &[i32],
    lin: &Lin,
    history: Option<(&[i32], &mut [i32], &Difference)>,
) -> (u32, u32) {
    let own = lin.own.unwrap_or_default();
    let mut or = 0;
    for (ui, &vi) in u.iter_mut().zip(v) {
        *ui = lin.term.apply_rounded(vi).wrapping_add(own.apply(*ui));
        or |= magnitude_bits(*ui);
    }
    let mut dv_or = 0;
    if let Some((v0, out, dv)) = history {
        for ((o, &a), &b) in out.iter_mut().zip(v).zip(v0) {
            *o = dv.apply(a, b);
            dv_or |= magnitude_bits(*o);
        }
    }
    (or, dv_or)
}

/// a·2^(e_a − e) − b·2^(e_b − e) at exponent e, each rounded to nearest: a difference of two
/// blocks (the step's velocity change), e chosen from their bounds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Difference {
    pub e: i32,
    shift_a: i32,
    shift_b: i32,
}

impl Difference {
    /// The difference of blocks `a` and `b`, its exponent keeping |a| + |b| below 2^29 units.
    pub fn new(a: Block, b: Block) -> Difference {
        let parts = [
            magnitude_bound(Scalar::ONE, a),
            magnitude_bound(Scalar::ONE, b),
        ];
        let e = crate::superpose::exponent_for(&parts).unwrap_or(a.e);
        Difference {
            e,
            shift_a: e - a.e,
            shift_b: e - b.e,
        }
    }

    /// The result keeps the low 32 bits of the exact difference of the rounded terms, so each
    /// term is formed in `i32` ([`scale_low`]).
    #[inline(always)]
    pub fn apply(&self, a: i32, b: i32) -> i32 {
        scale_low(a, self.shift_a).wrapping_sub(scale_low(b, self.shift_b))
    }
}

/// The start's residual of a step with a history ([`residual_share`]): every term's shift onto
/// r₀'s exponent, and d₁'s narrowing for keeping it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ResidualPlan {
    /// r₀'s exponent.
    pub e: i32,
    /// d₁ (`i64` in Kp's lane, exponent `e_d`) onto e.
    d_shift: i32,
    /// r₀f (the last solve's residual, r) onto e, counted twice where the start is
    /// extrapolated (then also d₀ and r₋₁f from the history, each onto e); `None` without
    /// an extrapolated start.
    r_shift: i32,
    extrapolated: Option<(i32, i32)>,
    /// d₁ narrowed to 31 bits for the history, and its exponent.
    pub keep: Narrow,
    pub e_keep: i32,
}

impl ResidualPlan {
    /// The plan for d₁ (OR `d_or` at exponent `e_d`), r₀f (block `r`) and, extrapolating,
    /// d₀ and r₋₁f (blocks `d0`, `r1`).
    pub fn new(
        d_or: u64,
        e_d: i32,
        r: Block,
        extrapolated: Option<(Block, Block)>,
        sat: &mut u32,
    ) -> ResidualPlan {
        let (keep, offset, d_bound) = Narrow::new(crate::svu::bound_of_u64(d_or), sat);
        let d = Block {
            e: e_d + offset,
            bound: d_bound,
        };
        let twice = Block {
            e: r.e + 1,
            bound: r.bound,
        };
        let mut parts: heapless::Vec<(u32, i32), 4> = heapless::Vec::new();
        for b in [d, if extrapolated.is_some() { twice } else { r }] {
            let _ = parts.push(magnitude_bound(Scalar::ONE, b));
        }
        if let Some((d0, r1)) = extrapolated {
            let _ = parts.push(magnitude_bound(Scalar::ONE, d0));
            let _ = parts.push(magnitude_bound(Scalar::ONE, r1));
        }
        let e = crate::superpose::exponent_for(&parts).unwrap_or(r.e);
        ResidualPlan {
            e,
            d_shift: e - e_d,
            r_shift: e - r.e - i32::from(extrapolated.is_some()),
            extrapolated: extrapolated.map(|(d0, r1)| (e - d0.e, e - r1.e)),
            keep,
            e_keep: d.e,
        }
    }
}

/// The start's residual on one share for the extrapolated start v₀ + Δv₀:
/// r₀ = b₁ − S·(v₀ + Δv₀) = d₁ + 2·r₀f − d₀ − r₋₁f, since S·v₀ = b₀ − r₀f and
/// S·Δv₀ = d₀ − r₀f + r₋₁f (or, without a history, r₀ = d₁ + r₀f for v₀). r holds r₀f and
/// becomes r₀; the history takes d₁ (narrowed) and r₀f for the next step. Returns Σr₀² and
/// the OR of |r₀|.
pub fn residual_share<const R: usize>(
    r: &mut [i32],
    kp: &[[i64; R]],
    lane: usize,
    plan: &ResidualPlan,
    history: Option<(&mut [i32], &mut [i32])>,
) -> (u128, u32) {
    let mut or = 0;
    // v·2^(e_v − e) for a shift s = e − e_v, rounded to nearest. r₀ keeps the low 32 bits of
    // the sum of the terms, so each is formed as its low word: the `i32` ones in `i32`
    // ([`scale_low`]), d₁ (an `i64` below 2^62: the MVU's row sums) from its two words.
    let d_term = |v: i64| scale_low_wide(v, plan.d_shift);
    match history {
        Some((d_hist, r_hist)) => {
            for (((ri, ki), dh), rh) in r.iter_mut().zip(kp).zip(d_hist).zip(r_hist) {
                let d1 = ki[lane];
                let mut z = d_term(d1).wrapping_add(scale_low(*ri, plan.r_shift));
                if let Some((sd, sr)) = plan.extrapolated {
                    z = z.wrapping_sub(scale_low(*dh, sd).wrapping_add(scale_low(*rh, sr)));
                }
                *dh = plan.keep.apply(d1);
                *rh = *ri;
                *ri = z;
                or |= magnitude_bits(*ri);
            }
        }
        None => {
            for (ri, ki) in r.iter_mut().zip(kp) {
                *ri = d_term(ki[lane]).wrapping_add(scale_low(*ri, plan.r_shift));
                or |= magnitude_bits(*ri);
            }
        }
    }
    (sum_squares(r), or)
}

/// Pass A on one share, the start v₀ + Δv₀: v₀ kept in `v0`, then v ← `lin`(Δv) + v.
/// Returns the OR of |v|.
pub fn predict_share(v: &mut [i32], v0: &mut [i32], dv: &[i32], lin: Option<&Lin>) -> u32 {
    v0.copy_from_slice(v);
    let Some(lin) = lin else {
        return v.iter().fold(0, |o, &x| o | magnitude_bits(x));
    };
    let own = lin.own.unwrap_or_default();
    let mut or = 0;
    for (vi, &d) in v.iter_mut().zip(dv) {
        *vi = lin.term.apply_rounded(d).wrapping_add(own.apply(*vi));
        or |= magnitude_bits(*vi);
    }
    or
}

/// Σ|q| over a tool row's diagonal and couplings, in integers (exact: at most 1 + MAX_TOOL_ROW
/// values below 2^21), converted once.
fn row_magnitude(r: &deform_shared::live::ToolRow) -> f64 {
    let sum: u64 = core::iter::once(r.diagonal)
        .chain(r.row.iter().map(|c| c.value))
        .map(|q| u64::from(q.unsigned_abs()))
        .sum();
    sum as f64
}

/// A tool row's Σ raw·x over its diagonal (with `own`, the node's own value) and couplings
/// (values `x` at their columns): exact in `i64` (|raw| < 2^20, |x| < 2^31, ≤ 33 terms).
pub fn row_sum(row: &deform_shared::live::ToolRow, own: i32, x: &[i32]) -> i64 {
    let couplings: i64 = row
        .row
        .iter()
        .map(|c| i64::from(c.value) * i64::from(x.get(c.column as usize).copied().unwrap_or(0)))
        .sum();
    i64::from(row.diagonal) * i64::from(own) + couplings
}

#[cfg(test)]
mod tests {
    use super::*;
    use deform_shared::qformat::ldexp;

    #[test]
    fn pass_b_forms_the_momentum_minus_the_stiffness_impulse_and_its_change() {
        let v = [1 << 28, -(1 << 27), 12345, 0, -7];
        let ku: [i64; 5] = [1 << 40, -(3 << 38), 5, 0, (1 << 45) + 3];
        let b0 = [100, -200, 1 << 29, 0, 3];
        let (m, h) = (0.005, 1e-3);
        let (e_v, e_ku, e_b0) = (-40, -50, -30);
        let v_block = Block {
            e: e_v,
            bound: 1 << 28,
        };
        let ku_or = ku.iter().fold(0u64, |o, &k| o | (k ^ (k >> 63)) as u64);
        let mut sat = 0;
        let plan = RhsPlan::new(m, h, v_block, ku_or, e_ku, 0.0, e_b0, &mut sat);
        assert_eq!(sat, 0);
        let mut b = b0;
        let mut kp: std::vec::Vec<crate::kernel::Sums> = ku.iter().map(|&k| [0, k, 0]).collect();
        let sums = rhs_share(&mut b, &mut kp, &v, 1, &plan);
        for i in 0..5 {
            let want = m * ldexp(f64::from(v[i]), e_v) - h * ldexp(ku[i] as f64, e_ku);
            let got = ldexp(f64::from(b[i]), plan.e);
            assert!(
                (got - want).abs() <= ldexp(2.0, plan.e),
                "{i}: {got} vs {want}"
            );
            let d = ldexp(kp[i][1] as f64, plan.e_d);
            let want_d = got - ldexp(f64::from(b0[i]), e_b0);
            assert!(
                (d - want_d).abs() <= ldexp(1.0, plan.e_d),
                "{i}: {d} vs {want_d}"
            );
            assert!(b[i].unsigned_abs() < 1 << 30);
        }
        assert_eq!(sums.bb, sum_squares(&b));
    }
}
