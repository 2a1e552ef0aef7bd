//! Heterogeneous tissue: a stiffness value per node (N/m), from which each spring takes the mean
//! of its two end nodes ([`super::springs::MeanOfEndNodes`]).
//!
//! A field is a background value, overridden by spherical inclusions (in the order given, so a
//! later one wins where they overlap), overridden in turn by explicit per-node values (e.g. read
//! from a CSV map). The same K then serves all three displacement directions.

use super::grid::{Grid, Node};

/// A sphere of different stiffness, e.g. a stiff tumour in soft tissue. `center` and `radius`
/// are in node-index units; node (i, j, k) is inside when its distance from `center` is at most
/// `radius`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Inclusion {
    pub center: [f64; 3],
    pub radius: f64,
    pub k: f64,
}

impl Inclusion {
    pub fn contains(&self, node: Node) -> bool {
        let d2: f64 = [node.i, node.j, node.k]
            .iter()
            .zip(self.center)
            .map(|(&n, c)| (n as f64 - c).powi(2))
            .sum();
        d2 <= self.radius * self.radius
    }
}

/// The per-node stiffness of heterogeneous tissue.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeField {
    pub background: f64,
    pub inclusions: Vec<Inclusion>,
    /// Explicit values, applied last (a later entry for the same node wins).
    pub nodes: Vec<(Node, f64)>,
}

/// Why a stiffness field is unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum FieldError {
    #[error("the background stiffness {0} must be finite and greater than 0")]
    Background(f64),
    #[error("inclusion {index} (centre {center:?}) has stiffness {k} and radius {radius}; the stiffness must be finite and greater than 0, the radius finite and non-negative, the centre finite")]
    Inclusion {
        index: usize,
        center: [f64; 3],
        radius: f64,
        k: f64,
    },
    #[error("the stiffness {value} at node {node} must be finite and greater than 0")]
    NodeValue { node: Node, value: f64 },
    #[error("the stiffness value at node {node} is outside the {grid} grid")]
    NodeOutsideGrid { node: Node, grid: Grid },
}

fn positive(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

impl NodeField {
    /// A field with the same value everywhere.
    pub fn uniform(k: f64) -> Self {
        Self {
            background: k,
            inclusions: Vec::new(),
            nodes: Vec::new(),
        }
    }

    /// The stiffness of every node of `grid`, by global index.
    pub fn values(&self, grid: Grid) -> Result<Vec<f64>, FieldError> {
        if !positive(self.background) {
            return Err(FieldError::Background(self.background));
        }
        for (index, inc) in self.inclusions.iter().enumerate() {
            let ok = positive(inc.k)
                && inc.radius.is_finite()
                && inc.radius >= 0.0
                && inc.center.iter().all(|c| c.is_finite());
            if !ok {
                return Err(FieldError::Inclusion {
                    index,
                    center: inc.center,
                    radius: inc.radius,
                    k: inc.k,
                });
            }
        }
        let mut values: Vec<f64> = grid
            .nodes()
            .map(|node| {
                self.inclusions
                    .iter()
                    .rev()
                    .find(|inc| inc.contains(node))
                    .map_or(self.background, |inc| inc.k)
            })
            .collect();
        for &(node, value) in &self.nodes {
            let p = grid
                .index(node)
                .ok_or(FieldError::NodeOutsideGrid { node, grid })?;
            if !positive(value) {
                return Err(FieldError::NodeValue { node, value });
            }
            values[p] = value;
        }
        Ok(values)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inclusions_and_node_values_override_the_background() {
        let grid = Grid::new(3, 3, 3).unwrap();
        let field = NodeField {
            background: 1.0,
            inclusions: vec![Inclusion {
                center: [1.0, 1.0, 1.0],
                radius: 1.0,
                k: 5.0,
            }],
            nodes: vec![(Node::new(2, 2, 2), 7.0)],
        };
        let v = field.values(grid).unwrap();
        // The centre and its 6 axial neighbours are within distance 1; edge nodes are at √2.
        let inside: Vec<usize> = (0..27).filter(|&p| v[p] == 5.0).collect();
        assert_eq!(inside, vec![4, 10, 12, 13, 14, 16, 22]);
        assert_eq!(v[26], 7.0);
        assert_eq!(v.iter().filter(|&&k| k == 1.0).count(), 27 - 7 - 1);
    }

    #[test]
    fn refuses_bad_values() {
        let grid = Grid::new(2, 2, 2).unwrap();
        assert!(NodeField::uniform(0.0).values(grid).is_err());
        let mut f = NodeField::uniform(1.0);
        f.nodes.push((Node::new(2, 0, 0), 1.0));
        assert!(matches!(
            f.values(grid),
            Err(FieldError::NodeOutsideGrid { .. })
        ));
        let mut f = NodeField::uniform(1.0);
        f.inclusions.push(Inclusion {
            center: [0.0; 3],
            radius: -1.0,
            k: 2.0,
        });
        assert!(matches!(f.values(grid), Err(FieldError::Inclusion { .. })));
    }
}
