//! Conjugate symmetry (thesis 2.5 vi, 4.1): K is *persymmetric* when K_ij = K_{n−1−i,n−1−j},
//! i.e. K equals itself turned by 180°. Node p of an nx×ny×nz grid has the index
//! p = i + nx·(j + ny·k), so n−1−p is the node reflected through the grid's centre; a uniform
//! grid whose fixed (and prescribed) set is symmetric under that reflection therefore gives a
//! persymmetric K. Then the lower half B of the rows holds all of K: the word (i, j, v) also
//! stands for (n−1−i, n−1−j, v).
//!
//! The check is made on the *quantised* matrix and is exact (raw values compared as integers):
//! storing half is only right if the target's K is the mirror of itself bit for bit, and a
//! heterogeneous field or an asymmetric fixed set that only nearly mirrors must not pass.

use super::QuantizedMatrix;

/// Whether `q` is exactly persymmetric. Row n−1−i must hold row i's entries mirrored:
/// (n−1−j, v) for every (j, v), which in ascending column order is row i's list reversed.
pub fn is_persymmetric(q: &QuantizedMatrix) -> bool {
    let n = q.n;
    (0..n.div_ceil(2)).all(|i| {
        let (cols, raws) = q.row(i);
        let (mirror_cols, mirror_raws) = q.row(n - 1 - i);
        cols.len() == mirror_cols.len()
            && cols
                .iter()
                .zip(raws)
                .zip(mirror_cols.iter().rev().zip(mirror_raws.iter().rev()))
                .all(|((&c, &v), (&mc, &mv))| v == mv && c as usize == n - 1 - mc as usize)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::sparse::test_support::from_dense;
    use crate::model::{
        Connection, FixedNodeSet, Grid, Inclusion, Model, ModelSpec, Node, NodeField,
    };

    fn quantized(model: &Model) -> QuantizedMatrix {
        QuantizedMatrix::from_csr(model.unit_matrix()).unwrap()
    }

    fn spec(dims: (usize, usize, usize), connection: Connection) -> ModelSpec {
        let grid = Grid::new(dims.0, dims.1, dims.2).unwrap();
        ModelSpec {
            grid,
            connection,
            loads: vec![ModelSpec::default_load(grid)],
            ..ModelSpec::thesis_example()
        }
    }

    #[test]
    fn small_dense_cases() {
        let yes = from_dense(&[
            vec![2.0, -1.0, 0.0],
            vec![-1.0, 3.0, -1.0],
            vec![0.0, -1.0, 2.0],
        ]);
        assert!(is_persymmetric(&QuantizedMatrix::from_csr(&yes).unwrap()));
        let no = from_dense(&[
            vec![2.0, -1.0, 0.0],
            vec![-1.0, 3.0, -1.0],
            vec![0.0, -1.0, 2.5],
        ]);
        assert!(!is_persymmetric(&QuantizedMatrix::from_csr(&no).unwrap()));
        // Symmetric but not persymmetric: the pattern is not mirrored.
        let pattern = from_dense(&[
            vec![2.0, 0.0, -1.0, 0.0],
            vec![0.0, 2.0, 0.0, 0.0],
            vec![-1.0, 0.0, 2.0, 0.0],
            vec![0.0, 0.0, 0.0, 2.0],
        ]);
        assert!(!is_persymmetric(
            &QuantizedMatrix::from_csr(&pattern).unwrap()
        ));
    }

    #[test]
    fn uniform_grids_with_symmetric_fixed_sets_are_persymmetric() {
        for connection in [Connection::Axial, Connection::AxialShear] {
            for dims in [(10, 10, 10), (4, 5, 6), (3, 3, 3)] {
                let model = Model::build(&spec(dims, connection)).unwrap();
                assert!(is_persymmetric(&quantized(&model)), "{dims:?} {connection}");
            }
        }
        // Two opposite faces fixed: symmetric under the reflection through the centre.
        let both = ModelSpec {
            fixed_sets: vec![
                "z-".parse::<FixedNodeSet>().unwrap(),
                "z+".parse::<FixedNodeSet>().unwrap(),
            ],
            ..spec((6, 6, 6), Connection::AxialShear)
        };
        assert!(is_persymmetric(&quantized(&Model::build(&both).unwrap())));
    }

    #[test]
    fn asymmetric_fixed_sets_are_not() {
        let one_face = ModelSpec {
            fixed_sets: vec!["z-".parse::<FixedNodeSet>().unwrap()],
            ..spec((6, 6, 6), Connection::Axial)
        };
        assert!(!is_persymmetric(&quantized(
            &Model::build(&one_face).unwrap()
        )));
        let one_corner_more = ModelSpec {
            fixed_nodes: vec![Node::new(1, 0, 0)],
            ..spec((6, 6, 6), Connection::Axial)
        };
        assert!(!is_persymmetric(&quantized(
            &Model::build(&one_corner_more).unwrap()
        )));
    }

    #[test]
    fn heterogeneous_fields_are_not() {
        let field = ModelSpec {
            field: Some(NodeField {
                background: 1.0,
                inclusions: vec![Inclusion {
                    center: [1.0, 1.0, 1.0],
                    radius: 1.5,
                    k: 10.0,
                }],
                nodes: Vec::new(),
            }),
            ..spec((6, 6, 6), Connection::Axial)
        };
        assert!(!is_persymmetric(&quantized(&Model::build(&field).unwrap())));
    }
}
