//! The forward model of thesis chapter 2: a spring network on a node grid, its stiffness
//! matrix K per direction, fixed nodes and loads.
//!
//! # What to send, and why A rather than K
//!
//! For homogeneous tissue K_d = k_d·A (thesis eq. 38), where A ([`Model::unit_matrix`]) is the
//! Laplacian of unit springs with the fixed nodes applied. Since K_d·l̃ = f_d is the same system
//! as A·l̃ = f_d / k_d, the target holds one matrix, A, for all three directions and each
//! direction only scales its right-hand side by 1/k_d ([`Model::direction_scale`],
//! [`Model::scaled_rhs`]). A is also integer-valued, so it encodes exactly. The full K_d is
//! still available ([`Model::stiffness_matrix`]), for export, for checking, and for future
//! heterogeneous tissue where no such factorisation exists.
//!
//! Submodules: [`grid`] (numbering), [`springs`] (models A/B, per-spring stiffness),
//! [`assembly`] (the Laplacian), [`boundary`] (fixed nodes), [`loads`], [`elasticity`],
//! [`sparse`] (CSR), [`matrix_market`] (export).

pub mod assembly;
pub mod boundary;
pub mod elasticity;
pub mod grid;
pub mod loads;
pub mod matrix_market;
pub mod sparse;
pub mod springs;
mod triple;

use assembly::{assemble_laplacian, AssemblyError};
use boundary::{eliminate_fixed_nodes, fixed_node_mask};
use springs::{SpringStiffness, Uniform};

pub use boundary::FixedNodeSet;
pub use elasticity::Elasticity;
pub use grid::{Axis, Grid, Node};
pub use loads::PointLoad;
pub use sparse::Csr;
pub use springs::Connection;
pub use triple::TripleError;

/// Everything that defines a model: what the `deform model` flags describe.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelSpec {
    pub grid: Grid,
    pub connection: Connection,
    pub elasticity: Elasticity,
    /// Named node sets to fix (their union is fixed).
    pub fixed_sets: Vec<FixedNodeSet>,
    /// Individual nodes to fix, in addition to `fixed_sets`.
    pub fixed_nodes: Vec<Node>,
    /// Point loads; several at one node add up.
    pub loads: Vec<PointLoad>,
}

impl ModelSpec {
    /// The numerical example of thesis 2.6: a 10×10×10 cube, model A, k = (1, 2, 0.5) N/m, the
    /// eight corners fixed and 1 N in +x at the centre of the x = 0 face.
    /// One line for people: grid, spring network and elasticity.
    pub fn describe(&self) -> String {
        format!(
            "{} grid, {}, {}",
            self.grid, self.connection, self.elasticity
        )
    }

    pub fn thesis_example() -> Self {
        let grid = Grid::new(10, 10, 10).expect("10×10×10 is a valid grid");
        Self {
            grid,
            connection: Connection::Axial,
            elasticity: Elasticity::new(1.0, 2.0, 0.5).expect("positive elasticities"),
            fixed_sets: vec![FixedNodeSet::Corners],
            fixed_nodes: Vec::new(),
            loads: vec![Self::default_load(grid)],
        }
    }

    /// The thesis 2.6 load for any grid: 1 N in +x at node (0, ny/2, nz/2), the middle of the
    /// x = 0 face (rounded up to the higher node when the count is even).
    pub fn default_load(grid: Grid) -> PointLoad {
        PointLoad {
            node: Node::new(0, grid.ny() / 2, grid.nz() / 2),
            force: [1.0, 0.0, 0.0],
        }
    }
}

/// What a node named in a spec is for, to say which one is wrong.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NodeRole {
    Load,
    FixedNode,
}

impl std::fmt::Display for NodeRole {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            NodeRole::Load => "the load at node",
            NodeRole::FixedNode => "the fixed node",
        })
    }
}

/// Why a spec does not make a solvable model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ModelError {
    #[error("{role} {node} is outside the {grid} grid (valid indices: i < {}, j < {}, k < {})",
        grid.nx(), grid.ny(), grid.nz())]
    NodeOutsideGrid {
        role: NodeRole,
        node: Node,
        grid: Grid,
    },
    #[error("the load at node {node} has a non-finite force component")]
    NonFiniteLoad { node: Node },
    #[error("no node is fixed, so K is singular (the whole tissue could move freely); fix at least one node")]
    NoFixedNode,
    #[error("node {node} has no springs (a {grid} grid), so K is singular")]
    NodeWithoutSprings { node: Node, grid: Grid },
    #[error(transparent)]
    Assembly(#[from] AssemblyError),
}

/// An assembled homogeneous model: A with fixed nodes applied, and the loads.
#[derive(Debug, Clone)]
pub struct Model {
    spec: ModelSpec,
    fixed: Vec<bool>,
    unit_matrix: Csr,
    /// `[f_x, f_y, f_z]`, zero at fixed nodes.
    loads: [Vec<f64>; 3],
    loads_on_fixed_nodes: Vec<Node>,
}

impl Model {
    /// Checks `spec` and assembles A. Linear in the number of springs.
    pub fn build(spec: &ModelSpec) -> Result<Self, ModelError> {
        let grid = spec.grid;
        let outside = |role, node| ModelError::NodeOutsideGrid { role, node, grid };
        if let Some(&node) = spec.fixed_nodes.iter().find(|&&n| !grid.contains(n)) {
            return Err(outside(NodeRole::FixedNode, node));
        }
        for load in &spec.loads {
            if !grid.contains(load.node) {
                return Err(outside(NodeRole::Load, load.node));
            }
            if load.force.iter().any(|f| !f.is_finite()) {
                return Err(ModelError::NonFiniteLoad { node: load.node });
            }
        }
        let fixed = fixed_node_mask(grid, &spec.fixed_sets, &spec.fixed_nodes);
        if !fixed.contains(&true) {
            return Err(ModelError::NoFixedNode);
        }

        let unit_matrix = eliminate_fixed_nodes(&Self::free_matrix(spec, &Uniform(1.0))?, &fixed);
        // Model A or B on a grid is connected, so one fixed node makes K definite, unless a
        // node has no spring at all (only a 1×1×1 grid), whose row would then be all zero.
        if let Some(p) = unit_matrix.diagonal().iter().position(|&d| d <= 0.0) {
            return Err(ModelError::NodeWithoutSprings {
                node: grid.node(p),
                grid,
            });
        }

        let mut loads = loads::load_vectors(grid, &spec.loads);
        let mut loads_on_fixed_nodes = Vec::new();
        for (p, _) in fixed.iter().enumerate().filter(|(_, &f)| f) {
            if loads.iter().any(|f| f[p] != 0.0) {
                loads_on_fixed_nodes.push(grid.node(p));
            }
            for f in &mut loads {
                f[p] = 0.0;
            }
        }
        Ok(Self {
            spec: spec.clone(),
            fixed,
            unit_matrix,
            loads,
            loads_on_fixed_nodes,
        })
    }

    fn free_matrix(
        spec: &ModelSpec,
        stiffness: &impl SpringStiffness,
    ) -> Result<Csr, AssemblyError> {
        assemble_laplacian(spec.grid, spec.connection, stiffness)
    }

    pub fn spec(&self) -> &ModelSpec {
        &self.spec
    }

    pub fn grid(&self) -> Grid {
        self.spec.grid
    }

    /// The order n of K: one unknown per node and direction.
    pub fn n(&self) -> usize {
        self.spec.grid.node_count()
    }

    /// Grid coordinates of global index `p` (row p of K, entry p of every vector).
    pub fn node(&self, p: usize) -> Node {
        self.spec.grid.node(p)
    }

    /// Whether each node is fixed, by global index.
    pub fn fixed_mask(&self) -> &[bool] {
        &self.fixed
    }

    pub fn fixed_count(&self) -> usize {
        self.fixed.iter().filter(|&&f| f).count()
    }

    /// A: the unit-spring Laplacian with fixed nodes applied, the one matrix to send to the
    /// target for all three directions. K_d = [`Model::direction_scale`]`(d)`·A.
    pub fn unit_matrix(&self) -> &Csr {
        &self.unit_matrix
    }

    /// k_d, the factor with K_d = k_d·A; divide f_d by it to solve with A.
    pub fn direction_scale(&self, axis: Axis) -> f64 {
        self.spec.elasticity.along(axis)
    }

    /// The full K_d with fixed nodes applied, assembled spring by spring with stiffness k_d
    /// (equal to k_d·A up to rounding of the diagonal sums).
    pub fn stiffness_matrix(&self, axis: Axis) -> Csr {
        let free = Self::free_matrix(&self.spec, &Uniform(self.direction_scale(axis)))
            .expect("the elasticity is finite and positive");
        eliminate_fixed_nodes(&free, &self.fixed)
    }

    /// f_d, the load vector for direction `axis` (zero at fixed nodes): the right-hand side
    /// for K_d.
    pub fn load(&self, axis: Axis) -> &[f64] {
        &self.loads[axis.position()]
    }

    /// f_d / k_d: the right-hand side for A in direction `axis`, so that A·l̃ = f_d / k_d has
    /// the same solution l̃ as K_d·l̃ = f_d.
    pub fn scaled_rhs(&self, axis: Axis) -> Vec<f64> {
        let scale = self.direction_scale(axis);
        self.load(axis).iter().map(|f| f / scale).collect()
    }

    /// Nodes where a nonzero load was given but which are fixed: those loads were dropped.
    pub fn loads_on_fixed_nodes(&self) -> &[Node] {
        &self.loads_on_fixed_nodes
    }
}

#[cfg(test)]
mod tests {
    use super::sparse::test_support::to_dense;
    use super::*;

    fn spec(grid: (usize, usize, usize), connection: Connection) -> ModelSpec {
        let grid = Grid::new(grid.0, grid.1, grid.2).unwrap();
        ModelSpec {
            grid,
            connection,
            loads: vec![ModelSpec::default_load(grid)],
            ..ModelSpec::thesis_example()
        }
    }

    #[test]
    fn thesis_example_has_the_specified_load_and_fixed_nodes() {
        let model = Model::build(&ModelSpec::thesis_example()).unwrap();
        assert_eq!(model.n(), 1000);
        assert_eq!(model.fixed_count(), 8);
        for (p, &fixed) in model.fixed_mask().iter().enumerate() {
            let Node { i, j, k } = model.node(p);
            let corner = [i, j, k].iter().all(|&c| c == 0 || c == 9);
            assert_eq!(fixed, corner, "node {p}");
        }
        let loaded = model.grid().index(Node::new(0, 5, 5)).unwrap();
        for (p, &f) in model.load(Axis::X).iter().enumerate() {
            assert_eq!(f, if p == loaded { 1.0 } else { 0.0 });
        }
        assert!(model
            .load(Axis::Y)
            .iter()
            .chain(model.load(Axis::Z))
            .all(|&f| f == 0.0));
        assert_eq!(model.direction_scale(Axis::Y), 2.0);
        assert_eq!(model.scaled_rhs(Axis::X)[loaded], 1.0);
        assert!(model.loads_on_fixed_nodes().is_empty());
    }

    #[test]
    fn default_load_follows_the_grid() {
        let grid = Grid::new(4, 7, 3).unwrap();
        assert_eq!(ModelSpec::default_load(grid).node, Node::new(0, 3, 1));
    }

    #[test]
    fn stiffness_is_the_direction_scale_times_a() {
        for connection in [Connection::Axial, Connection::AxialShear] {
            let model = Model::build(&spec((4, 3, 5), connection)).unwrap();
            let a = model.unit_matrix();
            assert!(a.is_symmetric());
            for axis in Axis::ALL {
                let k = model.stiffness_matrix(axis);
                assert!(k.is_symmetric());
                assert_eq!(k, a.scaled(model.direction_scale(axis)));
            }
            let rhs = model.scaled_rhs(Axis::Z);
            let expected: Vec<f64> = model.load(Axis::Z).iter().map(|f| f / 0.5).collect();
            assert_eq!(rhs, expected);
        }
    }

    #[test]
    fn fixed_2x2x2_model_a_by_hand() {
        let mut s = spec((2, 2, 2), Connection::Axial);
        s.fixed_sets = vec![FixedNodeSet::None];
        s.fixed_nodes = vec![Node::new(0, 0, 0), Node::new(1, 1, 1)];
        s.loads = vec![
            "0,0,0:5,0,0".parse().unwrap(),
            "1,0,0:1,2,3".parse().unwrap(),
        ];
        let model = Model::build(&s).unwrap();
        #[rustfmt::skip]
        let expected = [
            [ 3.,  0.,  0.,  0.,  0.,  0.,  0.,  0.],
            [ 0.,  3.,  0., -1.,  0., -1.,  0.,  0.],
            [ 0.,  0.,  3., -1.,  0.,  0., -1.,  0.],
            [ 0., -1., -1.,  3.,  0.,  0.,  0.,  0.],
            [ 0.,  0.,  0.,  0.,  3., -1., -1.,  0.],
            [ 0., -1.,  0.,  0., -1.,  3.,  0.,  0.],
            [ 0.,  0., -1.,  0., -1.,  0.,  3.,  0.],
            [ 0.,  0.,  0.,  0.,  0.,  0.,  0.,  3.],
        ];
        assert_eq!(
            to_dense(model.unit_matrix()),
            expected.map(Vec::from).to_vec()
        );
        assert_eq!(model.load(Axis::X), &[0., 1., 0., 0., 0., 0., 0., 0.]);
        assert_eq!(model.load(Axis::Z)[1], 3.0);
        assert_eq!(model.loads_on_fixed_nodes(), &[Node::new(0, 0, 0)]);
    }

    #[test]
    fn refuses_unsolvable_specs() {
        let mut s = spec((3, 3, 3), Connection::Axial);
        s.loads = vec!["3,0,0:1,0,0".parse().unwrap()];
        let err = Model::build(&s).unwrap_err();
        assert!(matches!(
            err,
            ModelError::NodeOutsideGrid {
                role: NodeRole::Load,
                ..
            }
        ));
        assert!(err.to_string().contains("(3,0,0)"), "{err}");

        let mut s = spec((3, 3, 3), Connection::Axial);
        s.fixed_nodes = vec![Node::new(0, 0, 9)];
        assert!(matches!(
            Model::build(&s),
            Err(ModelError::NodeOutsideGrid {
                role: NodeRole::FixedNode,
                ..
            })
        ));

        let mut s = spec((3, 3, 3), Connection::Axial);
        s.fixed_sets = vec![FixedNodeSet::None];
        assert_eq!(Model::build(&s).unwrap_err(), ModelError::NoFixedNode);

        let mut s = spec((3, 3, 3), Connection::Axial);
        s.loads[0].force[1] = f64::NAN;
        assert!(matches!(
            Model::build(&s),
            Err(ModelError::NonFiniteLoad { .. })
        ));

        let s = spec((1, 1, 1), Connection::AxialShear);
        assert!(matches!(
            Model::build(&s),
            Err(ModelError::NodeWithoutSprings { .. })
        ));
    }

    #[test]
    fn a_load_only_on_fixed_nodes_gives_zero_right_hand_sides() {
        let mut s = spec((3, 3, 3), Connection::Axial);
        s.loads = vec!["0,0,0:1,1,1".parse().unwrap()];
        let model = Model::build(&s).unwrap();
        for axis in Axis::ALL {
            assert!(model.scaled_rhs(axis).iter().all(|&f| f == 0.0));
        }
        assert_eq!(model.loads_on_fixed_nodes(), &[Node::new(0, 0, 0)]);
    }

    #[test]
    fn a_line_of_nodes_is_fine() {
        let model = Model::build(&spec((1, 1, 5), Connection::AxialShear)).unwrap();
        assert_eq!(model.fixed_count(), 2);
        assert_eq!(
            model.unit_matrix().diagonal(),
            vec![1.0, 2.0, 2.0, 2.0, 1.0]
        );
    }
}
