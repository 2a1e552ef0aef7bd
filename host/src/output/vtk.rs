//! VTK XML output for ParaView: the grid with the displacement field as point data.
//!
//! - `.vtu` (unstructured grid): every node is a point, every grid cube a hexahedron (a grid
//!   that is flat in some direction gets one vertex cell per node instead);
//! - `.vts` (structured grid): the same points with the grid's extent, no explicit cells.
//!
//! Points sit at their grid coordinates (i, j, k), one unit per spring. Point data:
//! `displacement` (3-component vector, so ParaView's *Warp By Vector* shows the deformed
//! tissue), `magnitude` = |u| and `stiffness` (the node's stiffness in N/m). A time series is a
//! `.pvd` collection of one file per step ([`write_pvd`]), which ParaView plays as an animation.

use std::io::Write;
use std::path::Path;

use anyhow::{bail, Context};
use vtkio::model::{
    Attribute, Attributes, ByteOrder, CellType, Cells, DataArray, DataSet, Extent, Piece,
    StructuredGridPiece, UnstructuredGridPiece, Version, VertexNumbers, Vtk,
};

use super::file::write_atomic;
use super::NodeDisplacement;

/// Which VTK XML flavour to write.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VtkKind {
    Unstructured,
    Structured,
}

/// Grid dimensions spanned by `rows`, checked to be the whole grid in node-index order
/// (i fastest, then j, then k), which is also VTK's point order.
fn grid_dims(rows: &[NodeDisplacement]) -> anyhow::Result<[usize; 3]> {
    let Some(first) = rows.first() else {
        bail!("no nodes to write");
    };
    let dims = rows.iter().fold([0, 0, 0], |d, r| {
        [d[0].max(r.i + 1), d[1].max(r.j + 1), d[2].max(r.k + 1)]
    });
    let in_order = rows.iter().enumerate().all(|(p, r)| {
        r.i == p % dims[0] && r.j == (p / dims[0]) % dims[1] && r.k == p / (dims[0] * dims[1])
    });
    if rows.len() != dims.iter().product::<usize>() || !in_order || first.i + first.j + first.k != 0
    {
        bail!("the nodes do not form a whole grid in index order; VTK output needs every node");
    }
    Ok(dims)
}

/// Hexahedra over the grid (VTK's vertex order: the bottom face counter-clockwise, then the
/// top), or one vertex per point for a grid without volume.
fn cells(dims: [usize; 3]) -> Cells {
    let [nx, ny, nz] = dims;
    let index = |i: usize, j: usize, k: usize| (i + nx * (j + ny * k)) as u64;
    let mut connectivity = Vec::new();
    let mut offsets = Vec::new();
    let mut types = Vec::new();
    if nx >= 2 && ny >= 2 && nz >= 2 {
        for k in 0..nz - 1 {
            for j in 0..ny - 1 {
                for i in 0..nx - 1 {
                    connectivity.extend([
                        index(i, j, k),
                        index(i + 1, j, k),
                        index(i + 1, j + 1, k),
                        index(i, j + 1, k),
                        index(i, j, k + 1),
                        index(i + 1, j, k + 1),
                        index(i + 1, j + 1, k + 1),
                        index(i, j + 1, k + 1),
                    ]);
                    offsets.push(connectivity.len() as u64);
                    types.push(CellType::Hexahedron);
                }
            }
        }
    } else {
        for p in 0..(nx * ny * nz) as u64 {
            connectivity.push(p);
            offsets.push(p + 1);
            types.push(CellType::Vertex);
        }
    }
    Cells {
        cell_verts: VertexNumbers::XML {
            connectivity,
            offsets,
        },
        types,
    }
}

/// The VTK data set of `rows` (which must be the whole grid in node order).
pub fn data_set(rows: &[NodeDisplacement], kind: VtkKind) -> anyhow::Result<Vtk> {
    let dims = grid_dims(rows)?;
    let points: Vec<f64> = rows
        .iter()
        .flat_map(|r| [r.i as f64, r.j as f64, r.k as f64])
        .collect();
    let displacement: Vec<f64> = rows.iter().flat_map(|r| [r.ux, r.uy, r.uz]).collect();
    let magnitude: Vec<f64> = rows
        .iter()
        .map(|r| (r.ux * r.ux + r.uy * r.uy + r.uz * r.uz).sqrt())
        .collect();
    let stiffness: Vec<f64> = rows.iter().map(|r| r.stiffness).collect();
    let data = Attributes {
        point: vec![
            Attribute::DataArray(DataArray::vectors("displacement").with_data(displacement)),
            Attribute::DataArray(DataArray::scalars("magnitude", 1).with_data(magnitude)),
            Attribute::DataArray(DataArray::scalars("stiffness", 1).with_data(stiffness)),
        ],
        cell: Vec::new(),
    };
    let data = match kind {
        VtkKind::Unstructured => DataSet::inline(UnstructuredGridPiece {
            points: points.into(),
            cells: cells(dims),
            data,
        }),
        VtkKind::Structured => {
            let extent = Extent::Ranges([
                0..=(dims[0] as i32 - 1),
                0..=(dims[1] as i32 - 1),
                0..=(dims[2] as i32 - 1),
            ]);
            DataSet::StructuredGrid {
                extent: extent.clone(),
                meta: None,
                pieces: vec![Piece::Inline(Box::new(StructuredGridPiece {
                    extent,
                    points: points.into(),
                    data,
                }))],
            }
        }
    };
    Ok(Vtk {
        version: Version::new_xml(1, 0),
        title: "deform displacements".into(),
        byte_order: ByteOrder::LittleEndian,
        data,
        file_path: None,
    })
}

/// Writes `rows` as a `.vtu` or `.vts` file.
pub fn write_vtk(path: &Path, rows: &[NodeDisplacement], kind: VtkKind) -> anyhow::Result<()> {
    let data = data_set(rows, kind)?;
    write_atomic(path, |out| {
        data.write_xml(out)
            .with_context(|| format!("writing {}", path.display()))
    })
}

/// Writes a ParaView collection (`.pvd`) of `(time, file)` pairs; file names are written as
/// given, so make them relative to the `.pvd`'s directory.
pub fn write_pvd(path: &Path, steps: &[(f64, String)]) -> anyhow::Result<()> {
    write_atomic(path, |out| write_collection(out, steps))
}

fn write_collection(out: &mut impl Write, steps: &[(f64, String)]) -> anyhow::Result<()> {
    writeln!(out, r#"<?xml version="1.0"?>"#)?;
    writeln!(
        out,
        r#"<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">"#
    )?;
    writeln!(out, "  <Collection>")?;
    for (t, name) in steps {
        let name = name
            .replace('&', "&amp;")
            .replace('"', "&quot;")
            .replace('<', "&lt;");
        writeln!(
            out,
            r#"    <DataSet timestep="{t:e}" group="" part="0" file="{name}"/>"#
        )?;
    }
    writeln!(out, "  </Collection>")?;
    writeln!(out, "</VTKFile>")?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use vtkio::model::{ElementType, IOBuffer};

    fn rows(dims: [usize; 3]) -> Vec<NodeDisplacement> {
        (0..dims.iter().product::<usize>())
            .map(|p| {
                let (i, j, k) = (
                    p % dims[0],
                    (p / dims[0]) % dims[1],
                    p / (dims[0] * dims[1]),
                );
                NodeDisplacement {
                    i,
                    j,
                    k,
                    ux: 0.1 * i as f64,
                    uy: -0.01 * j as f64 + 1e-9,
                    uz: 3.5e-4 * (k * k) as f64,
                    stiffness: 1.0 + p as f64,
                }
            })
            .collect()
    }

    fn f64s(buf: &IOBuffer) -> Vec<f64> {
        match buf {
            IOBuffer::F64(v) => v.clone(),
            other => panic!("expected f64 data, got {other:?}"),
        }
    }

    /// Named point arrays: name, kind, values.
    type PointArrays = Vec<(String, ElementType, Vec<f64>)>;

    /// The point coordinates, the point arrays and the cell count of a read-back file.
    fn read_back(path: &Path) -> (Vec<f64>, PointArrays, usize) {
        let vtk = Vtk::import(path).unwrap();
        let (points, data, cells) = match vtk.data {
            DataSet::UnstructuredGrid { pieces, .. } => match pieces.into_iter().next().unwrap() {
                Piece::Inline(p) => (p.points, p.data, p.cells.types.len()),
                other => panic!("{other:?}"),
            },
            DataSet::StructuredGrid { pieces, .. } => match pieces.into_iter().next().unwrap() {
                Piece::Inline(p) => (p.points, p.data, 0),
                other => panic!("{other:?}"),
            },
            other => panic!("{other:?}"),
        };
        let arrays = data
            .point
            .into_iter()
            .map(|a| match a {
                Attribute::DataArray(a) => (a.name, a.elem, f64s(&a.data)),
                other => panic!("{other:?}"),
            })
            .collect();
        (f64s(&points), arrays, cells)
    }

    #[test]
    fn vtu_and_vts_read_back_with_points_and_point_data() {
        let dir = std::env::temp_dir().join(format!("deform-vtk-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let dims = [3, 4, 2];
        let rows = rows(dims);
        for (name, kind, cells) in [
            ("u.vtu", VtkKind::Unstructured, 2 * 3),
            ("u.vts", VtkKind::Structured, 0),
        ] {
            let path = dir.join(name);
            write_vtk(&path, &rows, kind).unwrap();
            let (points, arrays, n_cells) = read_back(&path);
            assert_eq!(n_cells, cells, "{name}");
            assert_eq!(points.len(), 3 * rows.len());
            for (r, xyz) in rows.iter().zip(points.chunks(3)) {
                assert_eq!(xyz, [r.i as f64, r.j as f64, r.k as f64]);
            }
            let names: Vec<&str> = arrays.iter().map(|a| a.0.as_str()).collect();
            assert_eq!(names, ["displacement", "magnitude", "stiffness"], "{name}");
            assert_eq!(arrays[0].1, ElementType::Vectors);
            let u = &arrays[0].2;
            assert_eq!(u.len(), 3 * rows.len());
            for (r, (uvw, (m, s))) in rows
                .iter()
                .zip(u.chunks(3).zip(arrays[1].2.iter().zip(&arrays[2].2)))
            {
                assert_eq!(uvw, [r.ux, r.uy, r.uz], "{name}: exact f64 round trip");
                let want = (r.ux * r.ux + r.uy * r.uy + r.uz * r.uz).sqrt();
                assert!((m - want).abs() <= 1e-15 * want.max(1.0));
                assert_eq!(*s, r.stiffness);
            }
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn a_flat_grid_gets_vertex_cells_and_a_partial_grid_is_refused() {
        let vtk = data_set(&rows([4, 1, 3]), VtkKind::Unstructured).unwrap();
        let DataSet::UnstructuredGrid { pieces, .. } = vtk.data else {
            panic!()
        };
        let Piece::Inline(piece) = &pieces[0] else {
            panic!()
        };
        assert_eq!(piece.cells.types, vec![CellType::Vertex; 12]);
        let mut partial = rows([2, 2, 2]);
        partial.pop();
        assert!(data_set(&partial, VtkKind::Unstructured).is_err());
        partial.swap(0, 1);
        assert!(data_set(&partial, VtkKind::Structured).is_err());
    }

    #[test]
    fn pvd_lists_the_steps() {
        let dir = std::env::temp_dir().join(format!("deform-pvd-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("series.pvd");
        write_pvd(
            &path,
            &[(0.5, "step_0001.vtu".into()), (1.0, "step_0002.vtu".into())],
        )
        .unwrap();
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.contains(r#"type="Collection""#));
        assert!(text.contains(r#"timestep="5e-1" group="" part="0" file="step_0001.vtu""#));
        assert!(text.contains(r#"file="step_0002.vtu""#));
        std::fs::remove_dir_all(&dir).ok();
    }
}
