//! Assembly of K for one displacement direction (thesis eqs. 24–30).
//!
//! Hooke's law per spring, f = k̃·(l̃_q − l̃_p), summed over a node's springs, gives the weighted
//! graph Laplacian of the spring network: K_pp = Σ k̃ over p's springs and K_pq = −k̃ for each
//! spring p–q. Every row sums to zero (a rigid translation stores no energy), so K is only
//! positive semidefinite until nodes are fixed (see [`super::boundary`]).

use super::grid::Grid;
use super::sparse::{Csr, CsrBuilder};
use super::springs::{Connection, SpringStiffness};

/// Why K could not be assembled.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AssemblyError {
    #[error("the spring between nodes {a} and {b} has stiffness {value}; it must be finite and non-negative")]
    InvalidSpringStiffness { a: usize, b: usize, value: f64 },
}

/// The free (no node fixed) stiffness matrix of the `connection` network on `grid`, with
/// `stiffness` giving each spring's k̃. Linear in the number of springs.
pub fn assemble_laplacian(
    grid: Grid,
    connection: Connection,
    stiffness: &impl SpringStiffness,
) -> Result<Csr, AssemblyError> {
    let n = grid.node_count();
    let mut builder = CsrBuilder::new(n, n * (connection.neighbour_count() + 1));
    let mut row = Vec::with_capacity(connection.neighbour_count() + 1);
    for (p, node) in grid.nodes().enumerate() {
        row.clear();
        let mut diagonal = 0.0;
        for q in connection.neighbours(grid, node) {
            let value = stiffness.between(p.min(q), p.max(q));
            if !(value.is_finite() && value >= 0.0) {
                return Err(AssemblyError::InvalidSpringStiffness {
                    a: p.min(q),
                    b: p.max(q),
                    value,
                });
            }
            if value > 0.0 {
                row.push((q, -value));
                diagonal += value;
            }
        }
        row.push((p, diagonal));
        builder
            .push_row(row.iter().copied())
            .expect("neighbours are inside the grid and rows come in order");
    }
    Ok(builder.finish().expect("one row per node"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::grid::Node;
    use crate::model::sparse::test_support::to_dense;
    use crate::model::springs::{MeanOfEndNodes, Uniform};

    fn unit(nx: usize, ny: usize, nz: usize, connection: Connection) -> Csr {
        assemble_laplacian(Grid::new(nx, ny, nz).unwrap(), connection, &Uniform(1.0)).unwrap()
    }

    /// 2×2×2, model A: node p = i + 2j + 4k is joined to p^1 (x), p^2 (y) and p^4 (z).
    #[test]
    fn hand_computed_2x2x2_model_a() {
        #[rustfmt::skip]
        let expected = [
            [ 3., -1., -1.,  0., -1.,  0.,  0.,  0.],
            [-1.,  3.,  0., -1.,  0., -1.,  0.,  0.],
            [-1.,  0.,  3., -1.,  0.,  0., -1.,  0.],
            [ 0., -1., -1.,  3.,  0.,  0.,  0., -1.],
            [-1.,  0.,  0.,  0.,  3., -1., -1.,  0.],
            [ 0., -1.,  0.,  0., -1.,  3.,  0., -1.],
            [ 0.,  0., -1.,  0., -1.,  0.,  3., -1.],
            [ 0.,  0.,  0., -1.,  0., -1., -1.,  3.],
        ];
        let k = unit(2, 2, 2, Connection::Axial);
        assert_eq!(to_dense(&k), expected.map(Vec::from).to_vec());
        assert_eq!(k.nnz(), 32);
    }

    /// 2×2×2, model B: every pair of the 8 nodes is a face, edge or corner neighbour.
    #[test]
    fn hand_computed_2x2x2_model_b() {
        #[rustfmt::skip]
        let expected = [
            [ 7., -1., -1., -1., -1., -1., -1., -1.],
            [-1.,  7., -1., -1., -1., -1., -1., -1.],
            [-1., -1.,  7., -1., -1., -1., -1., -1.],
            [-1., -1., -1.,  7., -1., -1., -1., -1.],
            [-1., -1., -1., -1.,  7., -1., -1., -1.],
            [-1., -1., -1., -1., -1.,  7., -1., -1.],
            [-1., -1., -1., -1., -1., -1.,  7., -1.],
            [-1., -1., -1., -1., -1., -1., -1.,  7.],
        ];
        let k = unit(2, 2, 2, Connection::AxialShear);
        assert_eq!(to_dense(&k), expected.map(Vec::from).to_vec());
    }

    #[test]
    fn spot_check_3x3x3() {
        let g = Grid::new(3, 3, 3).unwrap();
        let at = |i, j, k| g.index(Node::new(i, j, k)).unwrap();
        let a = unit(3, 3, 3, Connection::Axial);
        let centre = at(1, 1, 1);
        assert_eq!(centre, 13);
        assert_eq!(a.row(centre).0, &[4, 10, 12, 13, 14, 16, 22]);
        assert_eq!(a.get(centre, centre), 6.0);
        assert_eq!(a.get(centre, at(1, 1, 0)), -1.0);
        assert_eq!(a.get(centre, at(0, 0, 0)), 0.0);
        assert_eq!(a.get(0, 0), 3.0);
        assert_eq!(a.get(at(1, 0, 0), at(1, 0, 0)), 4.0);

        let b = unit(3, 3, 3, Connection::AxialShear);
        assert_eq!(b.row(centre).0, (0..27).collect::<Vec<_>>().as_slice());
        assert_eq!(b.get(centre, centre), 26.0);
        assert_eq!(b.get(centre, at(0, 0, 0)), -1.0);
        assert_eq!(b.get(0, 0), 7.0);
        assert_eq!(b.get(at(1, 0, 0), at(1, 0, 0)), 11.0);
        assert_eq!(b.get(at(1, 1, 0), at(1, 1, 0)), 17.0);
        assert_eq!(b.get(0, at(2, 0, 0)), 0.0);
        assert_eq!(b.get(0, at(1, 1, 1)), -1.0);
        // 8 corners with 7 springs, 12 edge nodes with 11, 6 face centres with 17, the centre with 26.
        assert_eq!(b.nnz(), 8 * 8 + 12 * 12 + 6 * 18 + 27);
    }

    #[test]
    fn symmetric_with_zero_row_sums_and_full_interior_rows() {
        for connection in [Connection::Axial, Connection::AxialShear] {
            let grid = Grid::new(4, 5, 6).unwrap();
            let k = unit(4, 5, 6, connection);
            assert!(k.is_symmetric());
            for r in 0..k.n() {
                let sum: f64 = k.row(r).1.iter().sum();
                assert_eq!(sum, 0.0, "row {r}");
            }
            let interior = grid.index(Node::new(1, 2, 3)).unwrap();
            assert_eq!(k.row(interior).0.len(), connection.neighbour_count() + 1);
            assert_eq!(k.max_row_nnz(), connection.neighbour_count() + 1);
        }
    }

    #[test]
    fn bandwidth_of_the_10_cube() {
        assert_eq!(unit(10, 10, 10, Connection::Axial).bandwidth(), 100);
        assert_eq!(unit(10, 10, 10, Connection::AxialShear).bandwidth(), 111);
    }

    #[test]
    fn uniform_stiffness_scales_the_unit_laplacian() {
        let grid = Grid::new(3, 4, 2).unwrap();
        let a = assemble_laplacian(
            grid,
            Connection::AxialShear,
            &crate::model::springs::Uniform(1.0),
        )
        .unwrap();
        let k = assemble_laplacian(
            grid,
            Connection::AxialShear,
            &crate::model::springs::Uniform(0.5),
        )
        .unwrap();
        assert_eq!(k, a.scaled(0.5));
    }

    #[test]
    fn heterogeneous_springs_average_their_ends() {
        let grid = Grid::new(3, 1, 1).unwrap();
        let k = assemble_laplacian(
            grid,
            Connection::Axial,
            &MeanOfEndNodes(vec![1.0, 3.0, 5.0]),
        )
        .unwrap();
        #[rustfmt::skip]
        let expected = [
            [ 2., -2.,  0.],
            [-2.,  6., -4.],
            [ 0., -4.,  4.],
        ];
        assert_eq!(to_dense(&k), expected.map(Vec::from).to_vec());
        assert!(k.is_symmetric());
    }

    #[test]
    fn zero_springs_are_absent_and_bad_ones_refused() {
        let grid = Grid::new(3, 1, 1).unwrap();
        let k = assemble_laplacian(grid, Connection::Axial, &|a: usize, _b: usize| {
            if a == 0 {
                0.0
            } else {
                1.0
            }
        })
        .unwrap();
        assert_eq!(k.get(0, 1), 0.0);
        assert_eq!(k.row(0).0, &[0]);
        assert_eq!(k.get(0, 0), 0.0);
        assert_eq!(
            assemble_laplacian(grid, Connection::Axial, &Uniform(-1.0)),
            Err(AssemblyError::InvalidSpringStiffness {
                a: 0,
                b: 1,
                value: -1.0
            })
        );
        assert!(assemble_laplacian(grid, Connection::Axial, &Uniform(f64::NAN)).is_err());
    }
}
