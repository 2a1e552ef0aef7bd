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
//! [`assembly`] (the Laplacian), [`boundary`] (fixed nodes), [`prescribed`] (prescribed
//! displacements), [`loads`], [`elasticity`], [`field`] (heterogeneous stiffness: inclusions),
//! [`components`] (connected components: parts free to move rigidly), [`sparse`] (CSR), [`matrix_market`]
//! (export); `triple` (the `I,J,K` syntax of flag values, private).

pub mod assembly;
pub mod boundary;
pub mod components;
pub mod elasticity;
pub mod field;
pub mod flags;
pub mod grid;
pub mod loads;
pub mod matrix_market;
pub mod prescribed;
pub mod sparse;
pub mod springs;
mod triple;

use assembly::{assemble_laplacian, AssemblyError};
use boundary::{eliminate_fixed_nodes, fixed_node_mask};
use springs::{MeanOfEndNodes, SpringStiffness, Uniform};

pub use boundary::{Face, FixedNodeSet, Side};
pub use elasticity::Elasticity;
pub use field::{FieldError, Inclusion, NodeField};
pub use grid::{Axis, Grid, Node};
pub use loads::{FacePressure, PointLoad};
pub use prescribed::PrescribedDisplacement;
pub use sparse::Csr;
pub use springs::Connection;
pub use triple::TripleError;

/// Everything that defines a model: what the `deform model` flags and scenario files describe.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelSpec {
    pub grid: Grid,
    pub connection: Connection,
    /// Homogeneous tissue: k_x, k_y, k_z. Ignored when `field` is set.
    pub elasticity: Elasticity,
    /// Heterogeneous tissue: a per-node stiffness; each spring takes the mean of its end nodes
    /// and K is the same for all three directions. `None`: homogeneous (`elasticity`).
    pub field: Option<NodeField>,
    /// Named node sets to fix (their union is fixed).
    pub fixed_sets: Vec<FixedNodeSet>,
    /// Individual nodes to fix, in addition to `fixed_sets`.
    pub fixed_nodes: Vec<Node>,
    /// Nodes moved by a known, possibly non-zero displacement (eliminated like fixed nodes,
    /// their values moved to the right-hand side).
    pub prescribed: Vec<PrescribedDisplacement>,
    /// Point loads; several at one node add up.
    pub loads: Vec<PointLoad>,
    /// Face pressures (total force spread equally over a face's nodes); add to `loads`.
    pub pressures: Vec<FacePressure>,
}

impl ModelSpec {
    /// One line for people: grid, spring network and elasticity.
    pub fn describe(&self) -> String {
        let tissue = match &self.field {
            None => self.elasticity.to_string(),
            Some(field) => format!(
                "heterogeneous k (background {} N/m, {} inclusion(s), {} node value(s); same K in x, y, z)",
                field.background,
                field.inclusions.len(),
                field.nodes.len()
            ),
        };
        format!("{} grid, {}, {}", self.grid, self.connection, tissue)
    }

    /// The numerical example of thesis 2.6: a 10×10×10 cube, model A, k = (1, 2, 0.5) N/m, the
    /// eight corners fixed and 1 N in +x at the centre of the x = 0 face.
    pub fn thesis_example() -> Self {
        let grid = Grid::new(10, 10, 10).expect("10×10×10 is a valid grid");
        Self {
            grid,
            connection: Connection::Axial,
            elasticity: Elasticity::new(1.0, 2.0, 0.5).expect("positive elasticities"),
            field: None,
            fixed_sets: vec![FixedNodeSet::Corners],
            fixed_nodes: Vec::new(),
            prescribed: Vec::new(),
            loads: vec![Self::default_load(grid)],
            pressures: Vec::new(),
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
    Prescribed,
}

impl std::fmt::Display for NodeRole {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            NodeRole::Load => "the load at node",
            NodeRole::FixedNode => "the fixed node",
            NodeRole::Prescribed => "the prescribed displacement at node",
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
    #[error("the pressure on face {face} has a non-finite force component")]
    NonFinitePressure { face: Face },
    #[error("the prescribed displacement at node {node} has a non-finite component")]
    NonFiniteDisplacement { node: Node },
    #[error("node {node} is both fixed and given a prescribed displacement; drop one of them")]
    PrescribedNodeFixed { node: Node },
    #[error("node {node} is given two different prescribed displacements")]
    ConflictingDisplacements { node: Node },
    #[error("no node is fixed or prescribed, so K is singular (the whole tissue could move freely); fix at least one node")]
    NoFixedNode,
    #[error("the {size} connected node(s) around node {node} have no fixed or prescribed node, so K is singular (that part could move freely); fix a node there")]
    UnanchoredComponent { node: Node, size: usize },
    #[error("node {node} has no springs (a {grid} grid), so K is singular")]
    NodeWithoutSprings { node: Node, grid: Grid },
    #[error("stiffness field: {0}")]
    Field(#[from] FieldError),
    #[error(transparent)]
    Assembly(#[from] AssemblyError),
    #[error(
        "a {grid} grid of {connection} has {nodes} nodes and {nonzeros} nonzeros in K: building \
         it needs about {}, and this machine has {} available; give a smaller --grid",
        crate::memory::human(*needs),
        crate::memory::human(*available)
    )]
    TooLarge {
        grid: Grid,
        connection: Connection,
        nodes: u64,
        nonzeros: u64,
        needs: u64,
        available: u64,
    },
}

/// An assembled model: the matrix to send (A for homogeneous tissue, K for heterogeneous), the
/// boundary conditions and the right-hand sides.
#[derive(Debug, Clone)]
pub struct Model {
    spec: ModelSpec,
    fixed: Vec<bool>,
    /// The prescribed displacement of each node, if any.
    prescribed: Vec<Option<[f64; 3]>>,
    /// Per-node stiffness for heterogeneous tissue.
    node_stiffness: Option<Vec<f64>>,
    unit_matrix: Csr,
    /// `[f_x, f_y, f_z]`, zero at fixed and prescribed nodes.
    loads: [Vec<f64>; 3],
    /// The right-hand sides for `unit_matrix`: f_d / scale_d with prescribed values moved over.
    rhs: [Vec<f64>; 3],
    loads_on_fixed_nodes: Vec<Node>,
}

/// Refuses a model whose [`crate::memory::model_estimate`] exceeds `available` bytes (`None`: unknown,
/// nothing refused).
pub fn check_memory(
    grid: Grid,
    connection: Connection,
    available: Option<u64>,
) -> Result<(), ModelError> {
    let need = crate::memory::model_estimate(grid, connection);
    match available {
        Some(available) if need.bytes > available => Err(ModelError::TooLarge {
            grid,
            connection,
            nodes: need.nodes,
            nonzeros: need.nonzeros,
            needs: need.bytes,
            available,
        }),
        _ => Ok(()),
    }
}

impl Model {
    /// Checks `spec` and assembles the system. Linear in the number of springs. A model the
    /// machine's memory cannot hold is refused before anything is allocated ([`crate::memory`]).
    pub fn build(spec: &ModelSpec) -> Result<Self, ModelError> {
        let grid = spec.grid;
        check_memory(grid, spec.connection, crate::memory::available())?;
        check_loads(spec)?;
        let fixed = fixed_node_mask(grid, &spec.fixed_sets, &spec.fixed_nodes);
        let prescribed = prescribed_values(spec, &fixed)?;
        let constrained: Vec<bool> = fixed
            .iter()
            .zip(&prescribed)
            .map(|(&f, p)| f || p.is_some())
            .collect();
        if !constrained.contains(&true) {
            return Err(ModelError::NoFixedNode);
        }
        let node_stiffness = match &spec.field {
            None => None,
            Some(field) => Some(field.values(grid)?),
        };
        let free = match &node_stiffness {
            None => Self::free_matrix(spec, &Uniform(1.0))?,
            Some(values) => Self::free_matrix(spec, &MeanOfEndNodes(values.clone()))?,
        };
        check_anchored(grid, &free, &constrained)?;
        let unit_matrix = eliminate_fixed_nodes(&free, &constrained);
        // A node with no spring at all (only a 1×1×1 grid) has an all-zero row.
        if let Some(p) = unit_matrix.diagonal().iter().position(|&d| d <= 0.0) {
            return Err(ModelError::NodeWithoutSprings {
                node: grid.node(p),
                grid,
            });
        }
        let mut loads = loads::load_vectors(grid, &spec.loads);
        loads::add_pressures(grid, &spec.pressures, &mut loads);
        let mut loads_on_fixed_nodes = Vec::new();
        for (p, _) in constrained.iter().enumerate().filter(|(_, &f)| f) {
            if loads.iter().any(|f| f[p] != 0.0) {
                loads_on_fixed_nodes.push(grid.node(p));
            }
            for f in &mut loads {
                f[p] = 0.0;
            }
        }
        let rhs = scaled_rhs(spec, &free, &loads, &prescribed, &constrained);
        Ok(Self {
            spec: spec.clone(),
            fixed,
            prescribed,
            node_stiffness,
            unit_matrix,
            loads,
            rhs,
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

    /// Whether each node is fixed (held at zero), by global index. Prescribed nodes are not
    /// included; see [`Model::prescribed`].
    pub fn fixed_mask(&self) -> &[bool] {
        &self.fixed
    }

    pub fn fixed_count(&self) -> usize {
        self.fixed.iter().filter(|&&f| f).count()
    }

    /// The prescribed displacement of each node (`None` where the node is not prescribed).
    pub fn prescribed(&self) -> &[Option<[f64; 3]>] {
        &self.prescribed
    }

    pub fn prescribed_count(&self) -> usize {
        self.prescribed.iter().filter(|u| u.is_some()).count()
    }

    /// Whether the tissue is heterogeneous (a per-node stiffness field).
    pub fn is_heterogeneous(&self) -> bool {
        self.node_stiffness.is_some()
    }

    /// The stiffness of each node in N/m, for output as point data. Heterogeneous tissue: the
    /// field's values. Homogeneous tissue: k_x at every node (the y and z systems differ only
    /// by the factors k_y/k_x and k_z/k_x).
    pub fn node_stiffness(&self) -> Vec<f64> {
        match &self.node_stiffness {
            Some(values) => values.clone(),
            None => vec![self.spec.elasticity.along(Axis::X); self.n()],
        }
    }

    /// The one matrix to send to the target for all three directions, with fixed and
    /// prescribed nodes eliminated. Homogeneous tissue: A, the unit-spring Laplacian, and
    /// K_d = [`Model::direction_scale`]`(d)`·A (thesis eq. 38). Heterogeneous tissue: K itself
    /// (the same for every direction, scale 1).
    pub fn unit_matrix(&self) -> &Csr {
        &self.unit_matrix
    }

    /// k_d, the factor with K_d = k_d·A; the right-hand side is divided by it to solve with A.
    /// 1 for heterogeneous tissue, whose [`Model::unit_matrix`] already is K.
    pub fn direction_scale(&self, axis: Axis) -> f64 {
        match self.node_stiffness {
            None => self.spec.elasticity.along(axis),
            Some(_) => 1.0,
        }
    }

    /// The full K_d with fixed and prescribed nodes eliminated: for homogeneous tissue
    /// assembled spring by spring with stiffness k_d (equal to k_d·A up to rounding of the
    /// diagonal sums); for heterogeneous tissue the sent matrix itself.
    pub fn stiffness_matrix(&self, axis: Axis) -> Csr {
        if self.node_stiffness.is_some() {
            return self.unit_matrix.clone();
        }
        eliminate_fixed_nodes(&self.free_stiffness_matrix(axis), &self.constrained_mask())
    }

    /// K_d before any node is fixed (the whole spring network's Laplacian): what the
    /// dynamic stepper needs to apply K to displacements that include prescribed nodes.
    pub fn free_stiffness_matrix(&self, axis: Axis) -> Csr {
        match &self.node_stiffness {
            None => Self::free_matrix(&self.spec, &Uniform(self.direction_scale(axis))),
            Some(values) => Self::free_matrix(&self.spec, &MeanOfEndNodes(values.clone())),
        }
        .expect("the elasticity was checked when the model was built")
    }

    /// Whether each node is fixed or prescribed: the nodes eliminated from the system.
    pub fn constrained_mask(&self) -> Vec<bool> {
        self.fixed
            .iter()
            .zip(&self.prescribed)
            .map(|(&f, p)| f || p.is_some())
            .collect()
    }

    /// f_d, the external load vector for direction `axis` (point loads plus pressures, zero at
    /// fixed and prescribed nodes).
    pub fn load(&self, axis: Axis) -> &[f64] {
        &self.loads[axis.position()]
    }

    /// The right-hand side for [`Model::unit_matrix`] in direction `axis`: f_d / k_d, with each
    /// prescribed node j's value moved over (b_i −= A_ij·u_j for free i, b_j = A_jj·u_j), so that
    /// the solution equals u_j there and matches K_d·l̃ = f_d everywhere else.
    pub fn scaled_rhs(&self, axis: Axis) -> Vec<f64> {
        self.rhs[axis.position()].clone()
    }

    /// Nodes where a nonzero load was given but which are fixed or prescribed: those loads
    /// were dropped.
    pub fn loads_on_fixed_nodes(&self) -> &[Node] {
        &self.loads_on_fixed_nodes
    }
}

/// Every fixed node and load inside the grid, every load and pressure finite.
fn check_loads(spec: &ModelSpec) -> Result<(), ModelError> {
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
    if let Some(p) = spec
        .pressures
        .iter()
        .find(|p| p.force.iter().any(|f| !f.is_finite()))
    {
        return Err(ModelError::NonFinitePressure { face: p.face });
    }
    Ok(())
}

/// Each node's prescribed displacement, checked: inside the grid, finite, not on a fixed
/// node, and one value per node.
fn prescribed_values(
    spec: &ModelSpec,
    fixed: &[bool],
) -> Result<Vec<Option<[f64; 3]>>, ModelError> {
    let grid = spec.grid;
    let mut prescribed: Vec<Option<[f64; 3]>> = vec![None; grid.node_count()];
    for d in &spec.prescribed {
        let p = grid.index(d.node).ok_or(ModelError::NodeOutsideGrid {
            role: NodeRole::Prescribed,
            node: d.node,
            grid,
        })?;
        if d.u.iter().any(|u| !u.is_finite()) {
            return Err(ModelError::NonFiniteDisplacement { node: d.node });
        }
        if fixed[p] {
            return Err(ModelError::PrescribedNodeFixed { node: d.node });
        }
        match prescribed[p] {
            Some(u) if u != d.u => {
                return Err(ModelError::ConflictingDisplacements { node: d.node })
            }
            _ => prescribed[p] = Some(d.u),
        }
    }
    Ok(prescribed)
}

/// Every connected part of the spring network needs a node held in place.
fn check_anchored(grid: Grid, free: &Csr, constrained: &[bool]) -> Result<(), ModelError> {
    let (label, count) = components::components(free);
    let mut anchored = vec![false; count];
    let mut size = vec![0usize; count];
    for (p, &c) in label.iter().enumerate() {
        anchored[c] |= constrained[p];
        size[c] += 1;
    }
    match anchored.iter().position(|&a| !a) {
        None => Ok(()),
        Some(c) => {
            let p = label.iter().position(|&l| l == c).expect("non-empty");
            Err(ModelError::UnanchoredComponent {
                node: grid.node(p),
                size: size[c],
            })
        }
    }
}

/// The right-hand sides of the unit matrix: the loads over k_d (a heterogeneous field's K is
/// the unit matrix itself), each prescribed displacement moved over (b_i −= K_ij·u_j for free
/// i, b_j = K_jj·u_j).
fn scaled_rhs(
    spec: &ModelSpec,
    free: &Csr,
    loads: &[Vec<f64>; 3],
    prescribed: &[Option<[f64; 3]>],
    constrained: &[bool],
) -> [Vec<f64>; 3] {
    let scales = Axis::ALL.map(|axis| match spec.field {
        None => spec.elasticity.along(axis),
        Some(_) => 1.0,
    });
    let mut rhs = [0, 1, 2].map(|d| loads[d].iter().map(|f| f / scales[d]).collect::<Vec<_>>());
    for (j, u) in prescribed
        .iter()
        .enumerate()
        .filter_map(|(j, u)| u.map(|u| (j, u)))
    {
        // K is symmetric, so column j of the free matrix is its row j.
        let (cols, vals) = free.row(j);
        for (&i, &kij) in cols.iter().zip(vals) {
            for d in 0..3 {
                if i == j {
                    rhs[d][j] = kij * u[d];
                } else if !constrained[i] {
                    rhs[d][i] -= kij * u[d];
                }
            }
        }
    }
    rhs
}

#[cfg(test)]
mod tests {
    use super::sparse::test_support::to_dense;
    use super::*;
    use crate::model::assembly::assemble_laplacian;

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

    /// 2×2×2, model A, x- fixed (nodes 0, 2, 4, 6), node (1,1,1) = 7 three times stiffer.
    /// Springs: 1–3 and 1–5 have k̃ = 1, 3–7 and 5–7 have (1 + 3)/2 = 2; to the fixed face
    /// 0–1, 2–3, 4–5 have 1 and 6–7 has 2.
    #[test]
    fn heterogeneous_2x2x2_model_a_by_hand() {
        let mut s = spec((2, 2, 2), Connection::Axial);
        s.fixed_sets = vec!["x-".parse().unwrap()];
        s.field = Some(NodeField {
            background: 1.0,
            inclusions: Vec::new(),
            nodes: vec![(Node::new(1, 1, 1), 3.0)],
        });
        let model = Model::build(&s).unwrap();
        #[rustfmt::skip]
        let expected = [
            [ 3.,  0.,  0.,  0.,  0.,  0.,  0.,  0.],
            [ 0.,  3.,  0., -1.,  0., -1.,  0.,  0.],
            [ 0.,  0.,  3.,  0.,  0.,  0.,  0.,  0.],
            [ 0., -1.,  0.,  4.,  0.,  0.,  0., -2.],
            [ 0.,  0.,  0.,  0.,  3.,  0.,  0.,  0.],
            [ 0., -1.,  0.,  0.,  0.,  4.,  0., -2.],
            [ 0.,  0.,  0.,  0.,  0.,  0.,  4.,  0.],
            [ 0.,  0.,  0., -2.,  0., -2.,  0.,  6.],
        ];
        assert_eq!(
            to_dense(model.unit_matrix()),
            expected.map(Vec::from).to_vec()
        );
        for axis in Axis::ALL {
            assert_eq!(model.direction_scale(axis), 1.0);
            assert_eq!(&model.stiffness_matrix(axis), model.unit_matrix());
        }
        assert_eq!(model.node_stiffness(), vec![1., 1., 1., 1., 1., 1., 1., 3.]);
        assert!(model.is_heterogeneous());
        assert!(s.describe().contains("heterogeneous"), "{}", s.describe());
    }

    /// 3×3×3, model B, z- fixed, a stiff inclusion of radius 0 (only the centre node 13, k = 5)
    /// in background 1: the centre's 26 springs have (1 + 5)/2 = 3.
    #[test]
    fn inclusion_3x3x3_model_b_by_hand() {
        let mut s = spec((3, 3, 3), Connection::AxialShear);
        s.fixed_sets = vec!["z-".parse().unwrap()];
        s.field = Some(NodeField {
            background: 1.0,
            inclusions: vec![Inclusion {
                center: [1.0, 1.0, 1.0],
                radius: 0.0,
                k: 5.0,
            }],
            nodes: Vec::new(),
        });
        let model = Model::build(&s).unwrap();
        let k = model.unit_matrix();
        assert!(k.is_symmetric());
        assert_eq!(k.get(13, 13), 26.0 * 3.0);
        assert_eq!(k.get(13, 22), -3.0); // (1,1,2), free
        assert_eq!(k.get(13, 26), -3.0); // (2,2,2), corner diagonal
        assert_eq!(k.get(13, 4), 0.0); // (1,1,0) is fixed
        assert_eq!(k.get(13, 0), 0.0);
        // (1,1,2): 17 springs, 16 of them to background nodes, one to the centre.
        assert_eq!(k.get(22, 22), 16.0 + 3.0);
        assert_eq!(k.get(22, 21), -1.0);
        // Fixed (1,1,0): only its diagonal, 16 + 3 as well.
        assert_eq!(k.row(4).0, &[4]);
        assert_eq!(k.get(4, 4), 19.0);
        // The free corner (0,0,2) = 18 has 7 springs: 6 of 1 and the diagonal to the centre, 3.
        assert_eq!(k.get(18, 18), 6.0 + 3.0);
        assert_eq!(k.get(18, 9), -1.0); // (0,0,1), free
        assert_eq!(k.get(18, 13), -3.0);
    }

    /// 2×2×2, model A, x- fixed, node 7 = (1,1,1) prescribed u = (1, 0, 0.5), 2 N in +x at
    /// node 1; k = (1, 2, 0.5). A has 3 on every diagonal; after eliminating 0, 2, 4, 6 and 7:
    /// rows 1: [3 at 1, −1 at 3, −1 at 5], 3: [−1 at 1, 3 at 3], 5: [−1 at 1, 3 at 5], 7: [3].
    /// b_x = f_x/k_x = 2 at node 1; node 7's neighbours 3 and 5 get −A·u = +1; b_7 = 3·1.
    #[test]
    fn prescribed_displacement_2x2x2_by_hand() {
        let mut s = spec((2, 2, 2), Connection::Axial);
        s.fixed_sets = vec!["x-".parse().unwrap()];
        s.prescribed = vec!["1,1,1:1,0,0.5".parse().unwrap()];
        s.loads = vec![
            "1,0,0:2,0,0".parse().unwrap(),
            "1,1,1:5,5,5".parse().unwrap(),
        ];
        let model = Model::build(&s).unwrap();
        #[rustfmt::skip]
        let expected = [
            [ 3.,  0.,  0.,  0.,  0.,  0.,  0.,  0.],
            [ 0.,  3.,  0., -1.,  0., -1.,  0.,  0.],
            [ 0.,  0.,  3.,  0.,  0.,  0.,  0.,  0.],
            [ 0., -1.,  0.,  3.,  0.,  0.,  0.,  0.],
            [ 0.,  0.,  0.,  0.,  3.,  0.,  0.,  0.],
            [ 0., -1.,  0.,  0.,  0.,  3.,  0.,  0.],
            [ 0.,  0.,  0.,  0.,  0.,  0.,  3.,  0.],
            [ 0.,  0.,  0.,  0.,  0.,  0.,  0.,  3.],
        ];
        assert_eq!(
            to_dense(model.unit_matrix()),
            expected.map(Vec::from).to_vec()
        );
        assert_eq!(
            model.scaled_rhs(Axis::X),
            vec![0., 2., 0., 1., 0., 1., 0., 3.]
        );
        assert_eq!(model.scaled_rhs(Axis::Y), vec![0.; 8]);
        assert_eq!(
            model.scaled_rhs(Axis::Z),
            vec![0., 0., 0., 0.5, 0., 0.5, 0., 1.5]
        );
        assert_eq!(model.loads_on_fixed_nodes(), &[Node::new(1, 1, 1)]);
        assert_eq!(model.prescribed_count(), 1);
        assert_eq!(model.fixed_count(), 4);

        // The solution holds the prescribed value and balances the free nodes of the full
        // system K_d·u = f_d.
        let free = assemble_laplacian(s.grid, s.connection, &Uniform(1.0)).unwrap();
        for axis in Axis::ALL {
            let u = super::sparse::test_support::dense_solve(
                model.unit_matrix(),
                &model.scaled_rhs(axis),
            );
            let want = s.prescribed[0].u[axis.position()];
            assert!((u[7] - want).abs() < 1e-12, "{axis}: {}", u[7]);
            let ku = free.scaled(model.direction_scale(axis)).mul_vec(&u);
            for p in [1, 3, 5] {
                assert!((ku[p] - model.load(axis)[p]).abs() < 1e-12, "{axis} {p}");
            }
            for p in [0, 2, 4, 6] {
                assert_eq!(u[p], 0.0);
            }
        }
    }

    #[test]
    fn a_pressure_loads_its_face_and_prescribed_nodes_anchor() {
        let mut s = spec((3, 3, 3), Connection::Axial);
        s.fixed_sets = vec![FixedNodeSet::None];
        s.loads = Vec::new();
        s.pressures = vec!["z+:0,0,-9".parse().unwrap()];
        assert_eq!(Model::build(&s).unwrap_err(), ModelError::NoFixedNode);
        s.prescribed = vec!["1,1,0:0,0,0".parse().unwrap()];
        let model = Model::build(&s).unwrap();
        assert_eq!(model.fixed_count(), 0);
        let fz = model.load(Axis::Z);
        assert_eq!(fz.iter().filter(|&&f| f == -1.0).count(), 9);
        assert_eq!(fz.iter().sum::<f64>(), -9.0);

        s.fixed_sets = vec!["z-".parse().unwrap()];
        assert_eq!(
            Model::build(&s).unwrap_err(),
            ModelError::PrescribedNodeFixed {
                node: Node::new(1, 1, 0)
            }
        );
        s.fixed_sets = vec![FixedNodeSet::None];
        s.prescribed.push("1,1,0:1,0,0".parse().unwrap());
        assert!(matches!(
            Model::build(&s),
            Err(ModelError::ConflictingDisplacements { .. })
        ));
        s.prescribed = vec!["1,1,3:0,0,0".parse().unwrap()];
        assert!(matches!(
            Model::build(&s),
            Err(ModelError::NodeOutsideGrid {
                role: NodeRole::Prescribed,
                ..
            })
        ));
    }

    #[test]
    fn homogeneous_node_stiffness_is_k_x() {
        let model = Model::build(&ModelSpec::thesis_example()).unwrap();
        assert_eq!(model.node_stiffness(), vec![1.0; 1000]);
        assert!(!model.is_heterogeneous());
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
