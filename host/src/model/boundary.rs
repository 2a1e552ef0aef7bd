//! Fixed nodes (zero-displacement boundary conditions) and their symmetric elimination.
//!
//! The free K is singular (a rigid translation costs nothing), so some nodes are held in place.
//! A fixed node p gets l̃_p = 0 by zeroing row p and column p of K except the diagonal, and
//! zeroing f_p. Zeroing the column as well as the row keeps K symmetric, which CG needs, and
//! keeping the diagonal keeps n unchanged and K definite: the fixed row just says
//! K_pp·l̃_p = 0. Because l̃_p = 0, dropping column p loses nothing from the other equations.

use std::fmt;
use std::str::FromStr;

use super::grid::{Axis, Grid, Node};
use super::sparse::{Csr, CsrBuilder};

/// Which end of an axis a face lies at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Side {
    /// Index 0 (`x-`, `y-`, `z-`).
    Low,
    /// The last index (`x+`, `y+`, `z+`).
    High,
}

/// One face of the grid box, e.g. `z+` (every node with k = nz − 1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Face {
    pub axis: Axis,
    pub side: Side,
}

impl Face {
    /// Whether `node` of `grid` lies on this face.
    pub fn contains(self, grid: Grid, node: Node) -> bool {
        FixedNodeSet::Face {
            axis: self.axis,
            side: self.side,
        }
        .contains(grid, node)
    }

    /// The global indices of this face's nodes, in index order.
    pub fn node_indices(self, grid: Grid) -> Vec<usize> {
        grid.nodes()
            .enumerate()
            .filter(|&(_, node)| self.contains(grid, node))
            .map(|(p, _)| p)
            .collect()
    }
}

impl fmt::Display for Face {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        FixedNodeSet::Face {
            axis: self.axis,
            side: self.side,
        }
        .fmt(f)
    }
}

/// Why a face name did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown face '{0}'; expected x-, x+, y-, y+, z- or z+")]
pub struct ParseFaceError(pub String);

impl FromStr for Face {
    type Err = ParseFaceError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        match text.parse::<FixedNodeSet>() {
            Ok(FixedNodeSet::Face { axis, side }) => Ok(Face { axis, side }),
            _ => Err(ParseFaceError(text.trim().to_string())),
        }
    }
}

/// A named set of nodes to fix; a `--fix` value is a comma-separated union of these.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum FixedNodeSet {
    /// Nothing; lets `--fix none` combined with `--fix-node` fix only the listed nodes.
    None,
    /// The 8 corners of the grid box (thesis 2.6).
    Corners,
    /// All nodes of one face, e.g. `x-` is every node with i = 0.
    Face { axis: Axis, side: Side },
}

impl FixedNodeSet {
    /// Whether `node` of `grid` belongs to this set.
    pub fn contains(self, grid: Grid, node: Node) -> bool {
        let at = |axis: Axis, side: Side| match side {
            Side::Low => node.along(axis) == 0,
            Side::High => node.along(axis) + 1 == grid.len_along(axis),
        };
        let at_either_end = |axis| at(axis, Side::Low) || at(axis, Side::High);
        match self {
            FixedNodeSet::None => false,
            FixedNodeSet::Corners => Axis::ALL.into_iter().all(at_either_end),
            FixedNodeSet::Face { axis, side } => at(axis, side),
        }
    }
}

impl fmt::Display for FixedNodeSet {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FixedNodeSet::None => f.write_str("none"),
            FixedNodeSet::Corners => f.write_str("corners"),
            FixedNodeSet::Face { axis, side } => {
                let sign = if *side == Side::Low { '-' } else { '+' };
                write!(f, "{axis}{sign}")
            }
        }
    }
}

/// Why a `--fix` item did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("unknown fixed-node set '{0}'; expected corners, none, or a face x-, x+, y-, y+, z-, z+")]
pub struct ParseFixedNodeSetError(pub String);

impl FromStr for FixedNodeSet {
    type Err = ParseFixedNodeSetError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let face = |axis, side| Ok(FixedNodeSet::Face { axis, side });
        match text.trim() {
            "none" => Ok(FixedNodeSet::None),
            "corners" => Ok(FixedNodeSet::Corners),
            "x-" => face(Axis::X, Side::Low),
            "x+" => face(Axis::X, Side::High),
            "y-" => face(Axis::Y, Side::Low),
            "y+" => face(Axis::Y, Side::High),
            "z-" => face(Axis::Z, Side::Low),
            "z+" => face(Axis::Z, Side::High),
            other => Err(ParseFixedNodeSetError(other.to_string())),
        }
    }
}

/// Marks the nodes in the union of `sets` and `nodes` (every node must be inside `grid`).
pub fn fixed_node_mask(grid: Grid, sets: &[FixedNodeSet], nodes: &[Node]) -> Vec<bool> {
    let mut fixed: Vec<bool> = grid
        .nodes()
        .map(|node| sets.iter().any(|set| set.contains(grid, node)))
        .collect();
    for &node in nodes {
        let p = grid
            .index(node)
            .expect("fixed nodes are checked against the grid first");
        fixed[p] = true;
    }
    fixed
}

/// K with the rows and columns of fixed nodes zeroed except their diagonals (dropped from
/// storage, not kept as explicit zeros). Linear in nnz.
pub fn eliminate_fixed_nodes(k: &Csr, fixed: &[bool]) -> Csr {
    assert_eq!(fixed.len(), k.n(), "one fixed flag per row");
    let mut builder = CsrBuilder::new(k.n(), k.nnz());
    for (r, &row_fixed) in fixed.iter().enumerate() {
        let (cols, vals) = k.row(r);
        let kept = cols
            .iter()
            .zip(vals)
            .filter(|&(&c, _)| {
                if row_fixed {
                    c == r
                } else {
                    c == r || !fixed[c]
                }
            })
            .map(|(&c, &v)| (c, v));
        builder
            .push_row(kept)
            .expect("columns come from a valid matrix");
    }
    builder.finish().expect("one row per row of k")
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::assembly::assemble_laplacian;
    use crate::model::sparse::test_support::to_dense;
    use crate::model::springs::{Connection, Uniform};

    #[test]
    fn parses_every_set_and_refuses_others() {
        assert_eq!("corners".parse(), Ok(FixedNodeSet::Corners));
        assert_eq!("none".parse(), Ok(FixedNodeSet::None));
        for text in ["x-", "x+", "y-", "y+", "z-", "z+"] {
            let set: FixedNodeSet = text.parse().unwrap();
            assert_eq!(set.to_string(), text);
        }
        for bad in ["", "x", "corner", "X-", "w+"] {
            assert!(bad.parse::<FixedNodeSet>().is_err(), "{bad}");
        }
        let message = "edges".parse::<FixedNodeSet>().unwrap_err().to_string();
        assert!(
            message.contains("'edges'") && message.contains("x+"),
            "{message}"
        );
    }

    #[test]
    fn corner_and_face_membership() {
        let grid = Grid::new(3, 4, 5).unwrap();
        let corners = fixed_node_mask(grid, &[FixedNodeSet::Corners], &[]);
        assert_eq!(corners.iter().filter(|&&f| f).count(), 8);
        assert!(corners[grid.index(Node::new(2, 3, 4)).unwrap()]);
        assert!(corners[grid.index(Node::new(0, 3, 0)).unwrap()]);
        assert!(!corners[grid.index(Node::new(1, 0, 0)).unwrap()]);

        let x_high = fixed_node_mask(grid, &["x+".parse().unwrap()], &[]);
        assert_eq!(x_high.iter().filter(|&&f| f).count(), 4 * 5);
        assert!(grid
            .nodes()
            .zip(&x_high)
            .all(|(node, &f)| f == (node.i == 2)));

        let union = fixed_node_mask(
            grid,
            &[FixedNodeSet::Corners, "z-".parse().unwrap()],
            &[Node::new(1, 1, 2)],
        );
        assert_eq!(union.iter().filter(|&&f| f).count(), 3 * 4 + 4 + 1);
        assert!(fixed_node_mask(grid, &[FixedNodeSet::None], &[])
            .iter()
            .all(|&f| !f));
    }

    #[test]
    fn faces_parse_and_list_their_nodes() {
        let grid = Grid::new(2, 3, 4).unwrap();
        let z_high: Face = "z+".parse().unwrap();
        assert_eq!(z_high.to_string(), "z+");
        assert_eq!(z_high.node_indices(grid), (18..24).collect::<Vec<_>>());
        let x_low: Face = "x-".parse().unwrap();
        assert_eq!(x_low.node_indices(grid).len(), 12);
        assert!("corners".parse::<Face>().is_err());
        assert!("z".parse::<Face>().is_err());
    }

    #[test]
    fn degenerate_grids_have_fewer_corners() {
        let grid = Grid::new(1, 1, 4).unwrap();
        let corners = fixed_node_mask(grid, &[FixedNodeSet::Corners], &[]);
        assert_eq!(corners, vec![true, false, false, true]);
    }

    #[test]
    fn elimination_keeps_symmetry_and_diagonal() {
        let grid = Grid::new(3, 3, 3).unwrap();
        for connection in [Connection::Axial, Connection::AxialShear] {
            let free = assemble_laplacian(grid, connection, &Uniform(2.0)).unwrap();
            let fixed = fixed_node_mask(grid, &[FixedNodeSet::Corners, "y+".parse().unwrap()], &[]);
            let k = eliminate_fixed_nodes(&free, &fixed);
            assert_eq!(k.n(), free.n());
            assert!(k.is_symmetric());
            assert_eq!(k.diagonal(), free.diagonal());
            for (r, c, v) in free.entries() {
                let expected = if r != c && (fixed[r] || fixed[c]) {
                    0.0
                } else {
                    v
                };
                assert_eq!(k.get(r, c), expected, "({r},{c})");
            }
            for (p, _) in fixed.iter().enumerate().filter(|(_, &f)| f) {
                assert_eq!(k.row(p).0, &[p]);
            }
        }
    }

    #[test]
    fn eliminating_node_0_of_a_chain() {
        let grid = Grid::new(3, 1, 1).unwrap();
        let free = assemble_laplacian(grid, Connection::Axial, &Uniform(1.0)).unwrap();
        let k = eliminate_fixed_nodes(&free, &[true, false, false]);
        #[rustfmt::skip]
        let expected = [
            [1.,  0.,  0.],
            [0.,  2., -1.],
            [0., -1.,  1.],
        ];
        assert_eq!(to_dense(&k), expected.map(Vec::from).to_vec());
    }
}
