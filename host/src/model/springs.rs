//! The spring networks of thesis 2.4 (figure 2-5) and the per-spring stiffness k̃.
//!
//! Model A joins each node to its 6 axial neighbours; model B to all 26 neighbours of its 3×3×3
//! block (faces, edge diagonals and corner diagonals). Every spring is shared by its two end
//! nodes and has one stiffness, asked of a [`SpringStiffness`] once per spring and direction.
//! That indirection is what lets heterogeneous tissue ([`MeanOfEndNodes`]) use the same
//! assembly as the homogeneous case ([`Uniform`]).

use std::fmt;

use super::grid::{Grid, Node};

/// Which neighbours a node is joined to by springs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Connection {
    /// Model A (axial): the 6 face neighbours, i.e. offsets with exactly one nonzero component.
    Axial,
    /// Model B (axial-shear): all 26 neighbours, i.e. every nonzero offset in {−1, 0, 1}³.
    AxialShear,
}

impl Connection {
    /// The thesis's letter for this model.
    pub const fn letter(self) -> char {
        match self {
            Connection::Axial => 'A',
            Connection::AxialShear => 'B',
        }
    }

    /// How many springs an interior node has (so an interior row of K holds this plus one
    /// nonzeros).
    pub const fn neighbour_count(self) -> usize {
        match self {
            Connection::Axial => 6,
            Connection::AxialShear => 26,
        }
    }

    /// The offsets `(di, dj, dk)` of a node's spring partners.
    pub fn offsets(self) -> impl Iterator<Item = (isize, isize, isize)> {
        let all = (-1..=1)
            .flat_map(|dk| (-1..=1).flat_map(move |dj| (-1..=1).map(move |di| (di, dj, dk))));
        all.filter(move |&(di, dj, dk)| {
            let nonzero = [di, dj, dk].iter().filter(|&&d| d != 0).count();
            match self {
                Connection::Axial => nonzero == 1,
                Connection::AxialShear => nonzero >= 1,
            }
        })
    }

    /// The global indices of `node`'s spring partners inside `grid`.
    pub fn neighbours(self, grid: Grid, node: Node) -> impl Iterator<Item = usize> {
        self.offsets().filter_map(move |(di, dj, dk)| {
            grid.offset(node, di, dj, dk).and_then(|q| grid.index(q))
        })
    }
}

impl fmt::Display for Connection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Connection::Axial => write!(f, "model A (axial, 6 neighbours)"),
            Connection::AxialShear => write!(f, "model B (axial-shear, 26 neighbours)"),
        }
    }
}

/// The stiffness k̃ of the spring between two nodes, for one displacement direction.
///
/// Called with `a < b` (global indices) exactly once per spring, so an implementation need not
/// be symmetric itself; K is symmetric by construction. A stiffness of 0 means "no spring"
/// (nothing is stored); negative or non-finite values are refused by the assembly.
pub trait SpringStiffness {
    fn between(&self, a: usize, b: usize) -> f64;
}

/// Any `Fn(a, b) -> k̃` is a stiffness.
impl<F: Fn(usize, usize) -> f64> SpringStiffness for F {
    fn between(&self, a: usize, b: usize) -> f64 {
        self(a, b)
    }
}

/// Homogeneous tissue: every spring has the same stiffness (thesis eq. 38, K = k̃·A).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Uniform(pub f64);

impl SpringStiffness for Uniform {
    fn between(&self, _: usize, _: usize) -> f64 {
        self.0
    }
}

/// Heterogeneous tissue: each node carries an elasticity and a spring takes the mean of its
/// two end nodes' values. K then no longer factors as k̃·A, so the full K must be sent.
#[derive(Debug, Clone, PartialEq)]
pub struct MeanOfEndNodes(pub Vec<f64>);

impl SpringStiffness for MeanOfEndNodes {
    fn between(&self, a: usize, b: usize) -> f64 {
        0.5 * (self.0[a] + self.0[b])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn models_have_6_and_26_offsets() {
        assert_eq!(Connection::Axial.offsets().count(), 6);
        assert_eq!(Connection::AxialShear.offsets().count(), 26);
        assert!(Connection::Axial
            .offsets()
            .all(|(a, b, c)| a.abs() + b.abs() + c.abs() == 1));
    }

    #[test]
    fn neighbours_are_clipped_at_the_boundary() {
        let g = Grid::new(3, 3, 3).unwrap();
        let count = |c: Connection, n: Node| c.neighbours(g, n).count();
        assert_eq!(count(Connection::Axial, Node::new(1, 1, 1)), 6);
        assert_eq!(count(Connection::Axial, Node::new(0, 0, 0)), 3);
        assert_eq!(count(Connection::AxialShear, Node::new(1, 1, 1)), 26);
        assert_eq!(count(Connection::AxialShear, Node::new(0, 0, 0)), 7);
        assert_eq!(count(Connection::AxialShear, Node::new(1, 0, 0)), 11);
        assert_eq!(count(Connection::AxialShear, Node::new(1, 1, 0)), 17);
    }

    #[test]
    fn stiffness_sources() {
        assert_eq!(Uniform(2.5).between(3, 7), 2.5);
        assert_eq!(MeanOfEndNodes(vec![1.0, 3.0]).between(0, 1), 2.0);
        let by_closure = |a: usize, b: usize| (a + b) as f64;
        assert_eq!(by_closure.between(1, 2), 3.0);
    }
}
