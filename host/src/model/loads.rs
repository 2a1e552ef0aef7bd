//! External point loads f (thesis eq. 22's f^d at a node), one vector per direction.

use std::fmt;
use std::str::FromStr;

use super::boundary::Face;
use super::grid::{Axis, Grid, Node};
use super::triple::{parse_triple, TripleError};

/// A force `[fx, fy, fz]` (newtons) acting at one node.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointLoad {
    pub node: Node,
    pub force: [f64; 3],
}

impl PointLoad {
    /// The force component along `axis`.
    pub fn along(&self, axis: Axis) -> f64 {
        self.force[axis.position()]
    }
}

impl fmt::Display for PointLoad {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [fx, fy, fz] = self.force;
        write!(f, "({fx}, {fy}, {fz}) N at node {}", self.node)
    }
}

/// Why a `I,J,K:FX,FY,FZ` load did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParseLoadError {
    #[error("expected a load as I,J,K:FX,FY,FZ (node indices, a colon, force components in N)")]
    MissingColon,
    #[error("expected a load as I,J,K:FX,FY,FZ; in the node part I,J,K: {0}")]
    Node(TripleError),
    #[error("expected a load as I,J,K:FX,FY,FZ; in the force part FX,FY,FZ: {0}")]
    Force(TripleError),
    #[error("load force component {0} is not finite")]
    NotFinite(String),
}

impl FromStr for PointLoad {
    type Err = ParseLoadError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let (node, force) = text.split_once(':').ok_or(ParseLoadError::MissingColon)?;
        let [i, j, k] =
            parse_triple(node, "a non-negative integer").map_err(ParseLoadError::Node)?;
        let force: [f64; 3] = parse_triple(force, "a number").map_err(ParseLoadError::Force)?;
        if let Some(bad) = force.iter().find(|v| !v.is_finite()) {
            return Err(ParseLoadError::NotFinite(bad.to_string()));
        }
        Ok(PointLoad {
            node: Node { i, j, k },
            force,
        })
    }
}

/// A uniform pressure on one face of the grid: the total force `[fx, fy, fz]` (newtons) spread
/// equally over the face's nodes (each of the m nodes gets force / m).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FacePressure {
    pub face: Face,
    pub force: [f64; 3],
}

impl fmt::Display for FacePressure {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [fx, fy, fz] = self.force;
        write!(f, "({fx}, {fy}, {fz}) N in total over face {}", self.face)
    }
}

/// Why a `FACE:FX,FY,FZ` pressure did not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ParsePressureError {
    #[error("expected a pressure as FACE:FX,FY,FZ (a face x-, x+, y-, y+, z-, z+, a colon, the total force in N)")]
    MissingColon,
    #[error("expected a pressure as FACE:FX,FY,FZ: {0}")]
    Face(#[from] super::boundary::ParseFaceError),
    #[error("expected a pressure as FACE:FX,FY,FZ; in the force part FX,FY,FZ: {0}")]
    Force(TripleError),
    #[error("pressure force component {0} is not finite")]
    NotFinite(String),
}

impl FromStr for FacePressure {
    type Err = ParsePressureError;

    fn from_str(text: &str) -> Result<Self, Self::Err> {
        let (face, force) = text
            .split_once(':')
            .ok_or(ParsePressureError::MissingColon)?;
        let face: Face = face.parse()?;
        let force: [f64; 3] = parse_triple(force, "a number").map_err(ParsePressureError::Force)?;
        if let Some(bad) = force.iter().find(|v| !v.is_finite()) {
            return Err(ParsePressureError::NotFinite(bad.to_string()));
        }
        Ok(FacePressure { face, force })
    }
}

/// Adds each pressure's share (total force / number of face nodes) to every node of its face.
pub fn add_pressures(grid: Grid, pressures: &[FacePressure], vectors: &mut [Vec<f64>; 3]) {
    for pressure in pressures {
        let nodes = pressure.face.node_indices(grid);
        let share = 1.0 / nodes.len() as f64;
        for p in nodes {
            for axis in Axis::ALL {
                vectors[axis.position()][p] += pressure.force[axis.position()] * share;
            }
        }
    }
}

/// The load vectors `[f_x, f_y, f_z]` of `loads` on `grid`; loads at the same node add up.
/// Every load's node must be inside the grid.
pub fn load_vectors(grid: Grid, loads: &[PointLoad]) -> [Vec<f64>; 3] {
    let mut vectors = [(); 3].map(|_| vec![0.0; grid.node_count()]);
    for load in loads {
        let p = grid
            .index(load.node)
            .expect("load nodes are checked against the grid first");
        for axis in Axis::ALL {
            vectors[axis.position()][p] += load.along(axis);
        }
    }
    vectors
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_a_load() {
        assert_eq!(
            "0,5,5:1,0,-2.5".parse(),
            Ok(PointLoad {
                node: Node::new(0, 5, 5),
                force: [1.0, 0.0, -2.5]
            })
        );
        assert_eq!(
            " 1, 2, 3 : 1e-3, 0, 0".parse::<PointLoad>().unwrap().force,
            [1e-3, 0.0, 0.0]
        );
    }

    #[test]
    fn refuses_malformed_loads() {
        assert_eq!(
            "1,2,3".parse::<PointLoad>(),
            Err(ParseLoadError::MissingColon)
        );
        assert!(matches!(
            "1,2:1,0,0".parse::<PointLoad>(),
            Err(ParseLoadError::Node(_))
        ));
        assert!(matches!(
            "1,2,-3:1,0,0".parse::<PointLoad>(),
            Err(ParseLoadError::Node(_))
        ));
        assert!(matches!(
            "1,2,3:1,0".parse::<PointLoad>(),
            Err(ParseLoadError::Force(_))
        ));
        assert!(matches!(
            "1,2,3:1,a,0".parse::<PointLoad>(),
            Err(ParseLoadError::Force(_))
        ));
        assert!(matches!(
            "1,2,3:1:0,0".parse::<PointLoad>(),
            Err(ParseLoadError::Force(_))
        ));
        assert!(matches!(
            "1,2,3:inf,0,0".parse::<PointLoad>(),
            Err(ParseLoadError::NotFinite(_))
        ));
        assert!(matches!(
            "1,2,3:0,NaN,0".parse::<PointLoad>(),
            Err(ParseLoadError::NotFinite(_))
        ));
    }

    #[test]
    fn pressure_spreads_the_total_force_over_the_face() {
        let p: FacePressure = "z+:0,0,-1".parse().unwrap();
        assert_eq!(p.force, [0.0, 0.0, -1.0]);
        assert!(matches!(
            "z+".parse::<FacePressure>(),
            Err(ParsePressureError::MissingColon)
        ));
        assert!(matches!(
            "w:0,0,1".parse::<FacePressure>(),
            Err(ParsePressureError::Face(_))
        ));
        assert!(matches!(
            "x-:0,0".parse::<FacePressure>(),
            Err(ParsePressureError::Force(_))
        ));
        let grid = Grid::new(2, 2, 2).unwrap();
        let mut v = [(); 3].map(|_| vec![0.0; 8]);
        add_pressures(grid, &[p, "x-:2,0,0".parse().unwrap()], &mut v);
        assert_eq!(v[2], vec![0.0, 0.0, 0.0, 0.0, -0.25, -0.25, -0.25, -0.25]);
        assert_eq!(v[0], vec![0.5, 0.0, 0.5, 0.0, 0.5, 0.0, 0.5, 0.0]);
        assert!(v[1].iter().all(|&f| f == 0.0));
    }

    #[test]
    fn loads_at_one_node_add_up() {
        let grid = Grid::new(2, 2, 1).unwrap();
        let loads = [
            "1,1,0:1,2,3".parse().unwrap(),
            "1,1,0:0.5,0,-3".parse().unwrap(),
            "0,0,0:0,0,1".parse().unwrap(),
        ];
        let [fx, fy, fz] = load_vectors(grid, &loads);
        assert_eq!(fx, vec![0.0, 0.0, 0.0, 1.5]);
        assert_eq!(fy, vec![0.0, 0.0, 0.0, 2.0]);
        assert_eq!(fz, vec![1.0, 0.0, 0.0, 0.0]);
    }
}
