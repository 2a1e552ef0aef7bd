//! Regularisation of the spring-field normal system (thesis 3.3), `--regularise KIND:WEIGHT`.
//!
//! Eq. 54 has one unknown per spring but only one equation per free node, direction and set,
//! and a spring whose ends never move relative to each other in any observation is not
//! determined at all. Regularisation adds prior knowledge to H·k = b:
//!
//! - `tikhonov:W` adds λ·‖k − k₀‖² (H += λI, b += λk₀), k₀ the homogeneous equation-error
//!   estimate of the same data: springs the data do not determine stay at the mean stiffness.
//! - `smooth:W` adds λ·Σ (k_s − k_t)² over pairs of springs that share a node (H += λ·L, L the
//!   graph Laplacian of that adjacency; its pattern is H's own, so the band stays as it is):
//!   neighbouring springs are alike unless the data say otherwise. This suppresses the
//!   node-to-node oscillation that noise causes.
//!
//! λ = W · (mean diagonal of H), so W is relative to the data's own weight and does not depend
//! on units or on the number of sets. When it is needed: whenever the unregularised solve is
//! refused as singular (too few load cases, springs never stretched), and with noisy
//! displacements, where the unregularised per-spring values oscillate; W between 1e-3 and 1e-1
//! is typical (docs/RESULTS.md shows the tumour case).

use std::fmt;
use std::str::FromStr;

/// One regularisation term.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Regularisation {
    /// Towards the homogeneous estimate, weight W.
    Tikhonov(f64),
    /// Neighbouring springs alike, weight W.
    Smooth(f64),
}

impl Regularisation {
    pub fn weight(self) -> f64 {
        match self {
            Regularisation::Tikhonov(w) | Regularisation::Smooth(w) => w,
        }
    }
}

impl fmt::Display for Regularisation {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Regularisation::Tikhonov(w) => write!(f, "tikhonov:{w}"),
            Regularisation::Smooth(w) => write!(f, "smooth:{w}"),
        }
    }
}

/// Why a `--regularise` value did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("expected tikhonov:W or smooth:W with a weight W > 0 (e.g. smooth:0.01), got '{0}'")]
pub struct ParseRegularisationError(String);

impl FromStr for Regularisation {
    type Err = ParseRegularisationError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let bad = || ParseRegularisationError(text.to_string());
        let (kind, weight) = text.split_once(':').ok_or_else(bad)?;
        let weight: f64 = weight.trim().parse().map_err(|_| bad())?;
        if !(weight.is_finite() && weight > 0.0) {
            return Err(bad());
        }
        match kind.trim() {
            "tikhonov" => Ok(Regularisation::Tikhonov(weight)),
            "smooth" => Ok(Regularisation::Smooth(weight)),
            _ => Err(bad()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_refuses() {
        assert_eq!("smooth:0.01".parse(), Ok(Regularisation::Smooth(0.01)));
        assert_eq!("tikhonov: 2".parse(), Ok(Regularisation::Tikhonov(2.0)));
        assert_eq!(Regularisation::Smooth(0.5).to_string(), "smooth:0.5");
        for bad in [
            "smooth",
            "smooth:0",
            "smooth:-1",
            "ridge:1",
            "tikhonov:nan",
            "smooth:x",
        ] {
            let e = bad.parse::<Regularisation>().unwrap_err().to_string();
            assert!(e.contains("tikhonov:W"), "{bad}: {e}");
        }
    }
}
