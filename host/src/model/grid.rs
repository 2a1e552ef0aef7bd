//! The uniform node grid of thesis 2.2 and its global node numbering.
//!
//! Nodes are numbered x fastest, then y, then z: `index = i + nx·(j + ny·k)` (thesis eq. 27's
//! ordering of Δl̃). This numbering is what makes K band-diagonal with half-bandwidth about
//! nx·ny (model A) or nx·ny + nx + 1 (model B), which the 512-column tiles rely on.

use std::fmt;
use std::str::FromStr;

use super::triple::{parse_triple, TripleError};

/// The largest number of nodes a grid may have. Far beyond what the target can hold; it keeps
/// every index comfortably inside `u32` (instruction-word tiles, protocol lengths) and stops a
/// mistyped `--grid` from trying to allocate terabytes.
pub const MAX_NODES: u64 = 1 << 24;

/// One of the three axes, which is both a grid direction and a displacement direction d.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Axis {
    X,
    Y,
    Z,
}

impl Axis {
    pub const ALL: [Axis; 3] = [Axis::X, Axis::Y, Axis::Z];

    /// 0, 1, 2 for x, y, z: the position of this axis in `[x, y, z]` arrays.
    pub const fn position(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }

    pub const fn name(self) -> &'static str {
        match self {
            Axis::X => "x",
            Axis::Y => "y",
            Axis::Z => "z",
        }
    }
}

impl fmt::Display for Axis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A node's grid coordinates (thesis notation i, j, k), each 0-based.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Node {
    pub i: usize,
    pub j: usize,
    pub k: usize,
}

impl Node {
    pub const fn new(i: usize, j: usize, k: usize) -> Self {
        Self { i, j, k }
    }

    /// The coordinate along `axis`.
    pub const fn along(self, axis: Axis) -> usize {
        match axis {
            Axis::X => self.i,
            Axis::Y => self.j,
            Axis::Z => self.k,
        }
    }
}

impl fmt::Display for Node {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "({},{},{})", self.i, self.j, self.k)
    }
}

/// Why an `I,J,K` node did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("expected a node as I,J,K (three non-negative integer grid indices): {0}")]
pub struct ParseNodeError(#[from] pub TripleError);

impl FromStr for Node {
    type Err = ParseNodeError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let [i, j, k] = parse_triple(text, "a non-negative integer")?;
        Ok(Node { i, j, k })
    }
}

/// Why grid dimensions are unusable.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum GridError {
    #[error("grid {nx}×{ny}×{nz} has a zero dimension; every dimension needs at least one node")]
    ZeroDimension { nx: usize, ny: usize, nz: usize },
    #[error("grid {nx}×{ny}×{nz} has more nodes than the limit of {MAX_NODES} (2^24)")]
    TooLarge { nx: usize, ny: usize, nz: usize },
}

/// Why a `NX,NY,NZ` grid flag did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseGridError {
    #[error("expected the grid as NX,NY,NZ (three positive node counts): {0}")]
    Syntax(#[from] TripleError),
    #[error(transparent)]
    Invalid(#[from] GridError),
}

/// The dimensions of a node grid; always non-empty and at most [`MAX_NODES`] nodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Grid {
    nx: usize,
    ny: usize,
    nz: usize,
}

impl Grid {
    pub fn new(nx: usize, ny: usize, nz: usize) -> Result<Self, GridError> {
        if nx == 0 || ny == 0 || nz == 0 {
            return Err(GridError::ZeroDimension { nx, ny, nz });
        }
        // Two usize factors always fit a u128, a third may not: saturate.
        let nodes = (nx as u128 * ny as u128).saturating_mul(nz as u128);
        if nodes > MAX_NODES as u128 {
            return Err(GridError::TooLarge { nx, ny, nz });
        }
        Ok(Self { nx, ny, nz })
    }

    pub const fn nx(self) -> usize {
        self.nx
    }
    pub const fn ny(self) -> usize {
        self.ny
    }
    pub const fn nz(self) -> usize {
        self.nz
    }

    /// The number of nodes along `axis`.
    pub const fn len_along(self, axis: Axis) -> usize {
        match axis {
            Axis::X => self.nx,
            Axis::Y => self.ny,
            Axis::Z => self.nz,
        }
    }

    /// The number of nodes, which is also the order n of K.
    pub const fn node_count(self) -> usize {
        self.nx * self.ny * self.nz
    }

    pub const fn contains(self, node: Node) -> bool {
        node.i < self.nx && node.j < self.ny && node.k < self.nz
    }

    /// The global index of `node`, or `None` if it lies outside the grid.
    pub const fn index(self, node: Node) -> Option<usize> {
        if self.contains(node) {
            Some(node.i + self.nx * (node.j + self.ny * node.k))
        } else {
            None
        }
    }

    /// The coordinates of global index `index` (which must be below [`Grid::node_count`]).
    pub const fn node(self, index: usize) -> Node {
        Node {
            i: index % self.nx,
            j: (index / self.nx) % self.ny,
            k: index / (self.nx * self.ny),
        }
    }

    /// Every node in index order, so that `nodes().nth(p) == Some(node(p))`.
    pub fn nodes(self) -> impl Iterator<Item = Node> {
        (0..self.node_count()).map(move |p| self.node(p))
    }

    /// The node at offset `(di, dj, dk)` from `node`, if it is inside the grid.
    pub fn offset(self, node: Node, di: isize, dj: isize, dk: isize) -> Option<Node> {
        let shifted = Node {
            i: node.i.checked_add_signed(di)?,
            j: node.j.checked_add_signed(dj)?,
            k: node.k.checked_add_signed(dk)?,
        };
        self.contains(shifted).then_some(shifted)
    }
}

impl fmt::Display for Grid {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}×{}×{}", self.nx, self.ny, self.nz)
    }
}

impl FromStr for Grid {
    type Err = ParseGridError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let [nx, ny, nz] = parse_triple(text, "a positive integer")?;
        Ok(Grid::new(nx, ny, nz)?)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbering_is_x_fastest_then_y_then_z() {
        let g = Grid::new(3, 4, 5).unwrap();
        assert_eq!(g.index(Node::new(0, 0, 0)), Some(0));
        assert_eq!(g.index(Node::new(1, 0, 0)), Some(1));
        assert_eq!(g.index(Node::new(0, 1, 0)), Some(3));
        assert_eq!(g.index(Node::new(0, 0, 1)), Some(12));
        assert_eq!(g.index(Node::new(2, 3, 4)), Some(59));
        assert_eq!(g.index(Node::new(3, 0, 0)), None);
        for (p, node) in g.nodes().enumerate() {
            assert_eq!(g.index(node), Some(p));
            assert_eq!(g.node(p), node);
        }
    }

    #[test]
    fn offsets_stay_inside() {
        let g = Grid::new(2, 2, 2).unwrap();
        assert_eq!(g.offset(Node::new(0, 0, 0), -1, 0, 0), None);
        assert_eq!(
            g.offset(Node::new(0, 0, 0), 1, 1, 1),
            Some(Node::new(1, 1, 1))
        );
        assert_eq!(g.offset(Node::new(1, 1, 1), 1, 0, 0), None);
    }

    #[test]
    fn refuses_empty_and_huge_grids() {
        assert_eq!(
            Grid::new(3, 0, 2),
            Err(GridError::ZeroDimension {
                nx: 3,
                ny: 0,
                nz: 2
            })
        );
        assert!(Grid::new(256, 256, 256).is_ok());
        assert!(matches!(
            Grid::new(256, 256, 257),
            Err(GridError::TooLarge { .. })
        ));
        assert!(matches!(
            Grid::new(usize::MAX, usize::MAX, usize::MAX),
            Err(GridError::TooLarge { .. })
        ));
    }

    #[test]
    fn parses_grid_and_node_flags() {
        assert_eq!(
            "10,10,10".parse::<Grid>(),
            Grid::new(10, 10, 10).map_err(Into::into)
        );
        assert_eq!("4,5,6".parse::<Node>(), Ok(Node::new(4, 5, 6)));
        assert!(matches!(
            "10,10".parse::<Grid>(),
            Err(ParseGridError::Syntax(TripleError::WrongCount { found: 2 }))
        ));
        assert!(matches!(
            "10,x,10".parse::<Grid>(),
            Err(ParseGridError::Syntax(TripleError::BadValue {
                position: 2,
                ..
            }))
        ));
        assert!(matches!(
            "10,0,10".parse::<Grid>(),
            Err(ParseGridError::Invalid(GridError::ZeroDimension { .. }))
        ));
        assert!(matches!(
            "1000,1000,1000".parse::<Grid>(),
            Err(ParseGridError::Invalid(GridError::TooLarge { .. }))
        ));
        assert!("1,2".parse::<Node>().is_err());
        assert!("1,2,-3".parse::<Node>().is_err());
        assert!("1.5,2,3".parse::<Node>().is_err());
        let message = "a,b,c".parse::<Node>().unwrap_err().to_string();
        assert!(message.contains("I,J,K"), "{message}");
    }
}
