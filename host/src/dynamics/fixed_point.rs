//! Whether the target's 21-bit matrix values can stand for S well enough.
//!
//! The target holds S_q, S rounded to one Q-format (`shared::qformat`, F chosen for max |S|).
//! Mixed-precision refinement converges when ρ = ‖S_q⁻¹·(S − S_q)‖ < 1, each round gaining a
//! factor ρ. S ⪰ M (C and K are semidefinite, and the eliminated rows keep their diagonal,
//! itself ≥ the node's mass), so ‖S⁻¹‖₂ ≤ 1/min m, and for the symmetric rounding error
//! E = S − S_q, ‖E‖₂ ≤ max row Σ|E_ij|. Requiring that bound to be ≤ 1/4 leaves S_q SPD and
//! refinement at least a factor 3 per round, whatever the right-hand side. It fails when a
//! tiny mass meets a large h²·K: the entries then span more than the 21 bits can hold.

use deform_shared::qformat::{choose_frac_bits, dequantize, quantize};

use super::params::DynamicsError;
use crate::model::Csr;

/// The bound ‖E‖/min m at or above which S is refused.
pub const MAX_CONTRACTION: f64 = 0.25;

/// Checks S (for step `h`, lumped masses `mass`) against the target's fixed point; returns
/// the contraction bound ρ.
pub fn check_representable(s: &Csr, mass: &[f64], h: f64) -> Result<f64, DynamicsError> {
    let unrepresentable = |reason: String| DynamicsError::Unrepresentable { h, reason };
    if let Some(v) = s.values().iter().find(|v| !v.is_finite()) {
        return Err(unrepresentable(format!("it has the non-finite entry {v}")));
    }
    let max = s.max_abs();
    let frac_bits = choose_frac_bits(max).map_err(|_| {
        unrepresentable(format!(
            "its largest entry {max:.3e} exceeds the format's range (2^20)"
        ))
    })?;
    let mut worst_row = 0.0f64;
    for r in 0..s.n() {
        let (_, vals) = s.row(r);
        let mut sum = 0.0;
        for &v in vals {
            let q = quantize(v, frac_bits)
                .and_then(|raw| dequantize(raw, frac_bits))
                .map_err(|e| unrepresentable(e.to_string()))?;
            sum += (q - v).abs();
        }
        worst_row = worst_row.max(sum);
    }
    let min_mass = mass.iter().copied().fold(f64::INFINITY, f64::min);
    let rho = worst_row / min_mass;
    if rho >= MAX_CONTRACTION {
        return Err(unrepresentable(format!(
            "its entries reach {max:.3e} while the smallest mass is {min_mass:.3e}, so rounding \
             to 2^-{frac_bits} could move S by {rho:.2} of its smallest eigenvalue (at most \
             {MAX_CONTRACTION} is safe)"
        )));
    }
    Ok(rho)
}
