//! Connected components of the spring graph (nodes joined by a nonzero off-diagonal of K).
//!
//! A component with no fixed or prescribed node can move rigidly at no cost, so K restricted to
//! it is singular. On a full grid models A and B are one component, but a heterogeneous field
//! with zero-stiffness springs, or future cut meshes, could split it.

use super::sparse::Csr;

/// The component number of every node (numbered 0.. in order of their lowest node) and the
/// number of components. Linear in nnz.
pub fn components(k: &Csr) -> (Vec<usize>, usize) {
    let n = k.n();
    let mut label = vec![usize::MAX; n];
    let mut count = 0;
    let mut stack = Vec::new();
    for start in 0..n {
        if label[start] != usize::MAX {
            continue;
        }
        label[start] = count;
        stack.push(start);
        while let Some(p) = stack.pop() {
            let (cols, vals) = k.row(p);
            for (&q, &v) in cols.iter().zip(vals) {
                if q != p && v != 0.0 && label[q] == usize::MAX {
                    label[q] = count;
                    stack.push(q);
                }
            }
        }
        count += 1;
    }
    (label, count)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::assembly::assemble_laplacian;
    use crate::model::grid::Grid;
    use crate::model::springs::{Connection, Uniform};

    #[test]
    fn a_grid_is_one_component_and_a_cut_chain_is_two() {
        let grid = Grid::new(3, 3, 3).unwrap();
        for c in [Connection::Axial, Connection::AxialShear] {
            let k = assemble_laplacian(grid, c, &Uniform(1.0)).unwrap();
            assert_eq!(components(&k).1, 1);
        }
        let chain = Grid::new(4, 1, 1).unwrap();
        let cut = |a: usize, _b: usize| if a == 1 { 0.0 } else { 1.0 };
        let k = assemble_laplacian(chain, Connection::Axial, &cut).unwrap();
        assert_eq!(components(&k), (vec![0, 0, 1, 1], 2));
    }
}
