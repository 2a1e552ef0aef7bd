//! Which nodes a live field frame carries, as `deform live --field` names them, and the
//! request that asks for them ([`deform_shared::field::FieldSelection`] is the shared check).

use std::fmt;
use std::str::FromStr;

use deform_shared::field::FieldSelection;

use crate::model::Grid;

/// `--field`: every node, the surface of the box grid, or every k-th node.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FieldChoice {
    #[default]
    All,
    Surface,
    Stride(u16),
}

impl FieldChoice {
    /// The `ReadField` stride and surface grid for a model on `grid`. A grid side past
    /// `u16::MAX` cannot be named on the wire: it is sent as `u16::MAX`, which the target
    /// refuses (`LiveError::BadGrid`).
    pub fn request(self, grid: &Grid) -> (u16, Option<[u16; 3]>) {
        let side = |d: usize| u16::try_from(d).unwrap_or(u16::MAX);
        match self {
            FieldChoice::All => (1, None),
            FieldChoice::Stride(k) => (k, None),
            FieldChoice::Surface => (1, Some([grid.nx(), grid.ny(), grid.nz()].map(side))),
        }
    }
}

impl FieldChoice {
    /// Per node of an n-node model on `grid`, whether a field frame carries it (all false if
    /// the selection does not fit: the target refuses it too).
    pub fn carried(self, grid: &Grid, n: usize) -> Vec<bool> {
        let mut carried = vec![false; n];
        let (stride, surface) = self.request(grid);
        if let Ok(selection) = FieldSelection::new(n as u32, stride, surface) {
            for offset in selection.chunk_offsets() {
                for p in selection.chunk(offset) {
                    carried[p as usize] = true;
                }
            }
        }
        carried
    }
}

impl FromStr for FieldChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "all" => Ok(FieldChoice::All),
            "surface" => Ok(FieldChoice::Surface),
            _ => {
                let k = s.strip_prefix("stride:").ok_or_else(|| {
                    format!("`{s}`: expected all, surface or stride:K (K from 1 to 65535)")
                })?;
                match k.parse::<u16>() {
                    Ok(k) if k >= 1 => Ok(FieldChoice::Stride(k)),
                    _ => Err(format!(
                        "`{s}`: the stride K must be a whole number from 1 to 65535"
                    )),
                }
            }
        }
    }
}

impl fmt::Display for FieldChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            FieldChoice::All => f.write_str("all"),
            FieldChoice::Surface => f.write_str("surface"),
            FieldChoice::Stride(k) => write!(f, "stride:{k}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_surface_of_a_cube_is_carried_and_its_inside_not() {
        let grid = Grid::new(4, 4, 4).unwrap();
        let carried = FieldChoice::Surface.carried(&grid, 64);
        assert_eq!(carried.iter().filter(|&&c| c).count(), 64 - 8);
        for (p, &c) in carried.iter().enumerate() {
            let n = grid.node(p);
            let inside = [n.i, n.j, n.k].iter().all(|&c| c == 1 || c == 2);
            assert_eq!(c, !inside, "{n:?}");
        }
        let every_third = FieldChoice::Stride(3).carried(&grid, 64);
        assert!(every_third
            .iter()
            .enumerate()
            .all(|(p, &c)| c == (p % 3 == 0)));
        assert!(FieldChoice::All.carried(&grid, 64).iter().all(|&c| c));
    }

    #[test]
    fn choices_parse_and_print_back() {
        for s in ["all", "surface", "stride:1", "stride:7", "stride:65535"] {
            assert_eq!(s.parse::<FieldChoice>().unwrap().to_string(), s);
        }
        for bad in [
            "",
            "stride:",
            "stride:0",
            "stride:-1",
            "stride:70000",
            "edges",
            "Stride:2",
        ] {
            assert!(bad.parse::<FieldChoice>().is_err(), "{bad}");
        }
    }
}
