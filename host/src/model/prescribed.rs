//! Prescribed non-zero displacements (a needle tip pushing tissue).
//!
//! A prescribed node j with known u_j is eliminated like a fixed node (row and column j of K
//! zeroed except the diagonal, so K stays symmetric), but its known value moves to the
//! right-hand side: b_i ← b_i − K_ij·u_j for every free i, and row j becomes K_jj·u_j = K_jj·u_j,
//! i.e. b_j = K_jj·u_j. The solution then equals u_j at that node. A fixed node is the special
//! case u_j = 0.

use std::fmt;
use std::str::FromStr;

use super::grid::Node;
use super::triple::{parse_triple, TripleError};

/// The displacement `[ux, uy, uz]` (grid units, like the solution) imposed on one node.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PrescribedDisplacement {
    pub node: Node,
    pub u: [f64; 3],
}

impl fmt::Display for PrescribedDisplacement {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [ux, uy, uz] = self.u;
        write!(f, "u = ({ux}, {uy}, {uz}) at node {}", self.node)
    }
}

/// Why an `I,J,K:UX,UY,UZ` displacement did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseDisplacementError {
    #[error("expected a displacement as I,J,K:UX,UY,UZ (node indices, a colon, displacement components)")]
    MissingColon,
    #[error("expected a displacement as I,J,K:UX,UY,UZ; in the node part I,J,K: {0}")]
    Node(TripleError),
    #[error("expected a displacement as I,J,K:UX,UY,UZ; in the displacement part UX,UY,UZ: {0}")]
    Value(TripleError),
    #[error("displacement component {0} is not finite")]
    NotFinite(String),
}

impl FromStr for PrescribedDisplacement {
    type Err = ParseDisplacementError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let (node, u) = text
            .split_once(':')
            .ok_or(ParseDisplacementError::MissingColon)?;
        let [i, j, k] =
            parse_triple(node, "a non-negative integer").map_err(ParseDisplacementError::Node)?;
        let u: [f64; 3] = parse_triple(u, "a number").map_err(ParseDisplacementError::Value)?;
        if let Some(bad) = u.iter().find(|v| !v.is_finite()) {
            return Err(ParseDisplacementError::NotFinite(bad.to_string()));
        }
        Ok(PrescribedDisplacement {
            node: Node { i, j, k },
            u,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_refuses() {
        assert_eq!(
            "5,5,9:0,0,-2".parse(),
            Ok(PrescribedDisplacement {
                node: Node::new(5, 5, 9),
                u: [0.0, 0.0, -2.0]
            })
        );
        assert_eq!(
            "5,5,9".parse::<PrescribedDisplacement>(),
            Err(ParseDisplacementError::MissingColon)
        );
        assert!(matches!(
            "5,5:0,0,0".parse::<PrescribedDisplacement>(),
            Err(ParseDisplacementError::Node(_))
        ));
        assert!(matches!(
            "5,5,5:0,0".parse::<PrescribedDisplacement>(),
            Err(ParseDisplacementError::Value(_))
        ));
        assert!(matches!(
            "5,5,5:0,inf,0".parse::<PrescribedDisplacement>(),
            Err(ParseDisplacementError::NotFinite(_))
        ));
    }
}
