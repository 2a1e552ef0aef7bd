//! Node fields in a scenario file: a background value, spherical inclusions over it and a CSV
//! map of per-node values, the form `[elasticity]` gives the stiffness in and `[dynamics]` the
//! masses and dampers in. One parser serves all three, and every message names the quantity
//! the field holds (a bad mass map is a mass error, not a stiffness one).

use std::collections::HashMap;
use std::ops::Range;
use std::path::Path;

use super::{Ctx, ScenarioError};
use crate::model::{Grid, Inclusion, Node, NodeField};

/// What a node field holds, for its messages.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Quantity {
    pub name: &'static str,
    pub unit: &'static str,
}

/// `[elasticity]`'s field: a spring takes the mean of its end nodes' stiffness.
pub const STIFFNESS: Quantity = Quantity {
    name: "stiffness",
    unit: "N/m",
};
/// `[dynamics] mass`: the lumped mass of a node.
pub const MASS: Quantity = Quantity {
    name: "mass",
    unit: "kg",
};
/// `[dynamics] damping`: the damper coefficient β beside the springs.
pub const DAMPING: Quantity = Quantity {
    name: "damper coefficient",
    unit: "N·s/m",
};

/// One spherical inclusion as the file gives it, with where.
pub(super) struct InclusionAt {
    pub center: [f64; 3],
    pub radius: f64,
    pub value: f64,
    pub span: Range<usize>,
}

/// A node field's parts as a table gives them, each with its span for messages.
pub(super) struct FieldParts<'a> {
    /// The table's key (`elasticity`, `dynamics.mass`, …) messages name: `KEY.background`,
    /// `KEY.inclusion`, `KEY.field` with `subkeys` (the `[elasticity]` table's own keys), else
    /// `KEY` itself (an inline `{ background, inclusion, field }` value).
    pub key: &'a str,
    pub subkeys: bool,
    pub quantity: Quantity,
    pub background: (f64, Range<usize>),
    pub inclusions: Vec<InclusionAt>,
    /// The CSV map's path, relative to the scenario file.
    pub csv: Option<(&'a str, Range<usize>)>,
}

fn positive(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

impl FieldParts<'_> {
    /// The field, checked: every value finite and greater than 0, every inclusion a sphere, the
    /// CSV map read against `grid`.
    pub fn resolve(self, cx: &Ctx<'_>, grid: Grid) -> Result<NodeField, ScenarioError> {
        let (q, key, sub) = (self.quantity, self.key, self.subkeys);
        let name = |part: &str| match sub {
            true => format!("{key}.{part}"),
            false => key.to_string(),
        };
        let (background, span) = self.background;
        if !positive(background) {
            return Err(cx.err(
                span,
                &name("background"),
                format!(
                    "the background {} must be finite and greater than 0 ({})",
                    q.name, q.unit
                ),
            ));
        }
        let mut field = NodeField::uniform(background);
        for inc in self.inclusions {
            let ok = positive(inc.value)
                && inc.radius.is_finite()
                && inc.radius >= 0.0
                && inc.center.iter().all(|c| c.is_finite());
            if !ok {
                return Err(cx.err(
                    inc.span,
                    &name("inclusion"),
                    format!(
                        "the {} must be finite and greater than 0, radius finite and \
                         non-negative, center finite",
                        q.name
                    ),
                ));
            }
            field.inclusions.push(Inclusion {
                center: inc.center,
                radius: inc.radius,
                k: inc.value,
            });
        }
        if let Some((csv, span)) = self.csv {
            let path = cx.path.parent().unwrap_or(Path::new("")).join(csv);
            field.nodes =
                read_node_field_csv(&path, grid, q).map_err(|m| cx.err(span, &name("field"), m))?;
        }
        Ok(field)
    }
}

/// Reads a node map: one `i,j,k,value` row per node (blank lines, `#` comments and a first
/// header line that does not parse are skipped). Errors name the CSV file and line, and the
/// quantity; a node given twice is refused with both lines.
pub fn read_node_field_csv(
    path: &Path,
    grid: Grid,
    quantity: Quantity,
) -> Result<Vec<(Node, f64)>, String> {
    let text = std::fs::read_to_string(path)
        .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    let mut out = Vec::new();
    let mut seen: HashMap<Node, usize> = HashMap::new();
    for (number, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let at = format!("{}:{}", path.display(), number + 1);
        let Some((node, value)) = parse_row(line) else {
            if out.is_empty() && number == 0 {
                continue; // a header
            }
            return Err(format!(
                "{at}: expected a row i,j,k,value (three node indices and a {} in {}), got '{line}'",
                quantity.name, quantity.unit
            ));
        };
        if !grid.contains(node) {
            return Err(format!("{at}: node {node} is outside the {grid} grid"));
        }
        if !positive(value) {
            return Err(format!(
                "{at}: {} {value} must be finite and greater than 0 ({})",
                quantity.name, quantity.unit
            ));
        }
        if let Some(first) = seen.insert(node, number + 1) {
            return Err(format!(
                "{at}: node {node} is given a second time (first on line {first}); give each \
                 node once"
            ));
        }
        out.push((node, value));
    }
    Ok(out)
}

/// `i,j,k,value`, or `None` if the line is not one.
fn parse_row(line: &str) -> Option<(Node, f64)> {
    let parts: Vec<&str> = line.split(',').map(str::trim).collect();
    let [i, j, k, value] = parts[..] else {
        return None;
    };
    Some((
        Node::new(i.parse().ok()?, j.parse().ok()?, k.parse().ok()?),
        value.parse().ok()?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn csv(name: &str, text: &str) -> std::path::PathBuf {
        let path = std::env::temp_dir().join(format!("deform-field-{}-{name}", std::process::id()));
        std::fs::write(&path, text).unwrap();
        path
    }

    #[test]
    fn a_map_names_its_quantity_and_refuses_a_node_given_twice() {
        let grid = Grid::new(3, 3, 3).unwrap();
        let good = csv("good.csv", "i,j,k,m\n0,0,0,0.5\n# note\n1,1,1,2\n");
        assert_eq!(
            read_node_field_csv(&good, grid, MASS).unwrap(),
            vec![(Node::new(0, 0, 0), 0.5), (Node::new(1, 1, 1), 2.0)]
        );
        let bad = csv("bad.csv", "0,0,0,-1\n");
        let e = read_node_field_csv(&bad, grid, MASS).unwrap_err();
        assert!(
            e.contains("bad.csv:1") && e.contains("mass -1") && e.contains("kg"),
            "{e}"
        );
        assert!(!e.contains("stiffness"), "{e}");
        let twice = csv("twice.csv", "0,0,0,1\n1,0,0,1\n\n0,0,0,2\n");
        let e = read_node_field_csv(&twice, grid, STIFFNESS).unwrap_err();
        assert!(e.contains("twice.csv:4") && e.contains("line 1"), "{e}");
        let short = csv("short.csv", "0,0,0,1\n0,0\n");
        let e = read_node_field_csv(&short, grid, DAMPING).unwrap_err();
        assert!(
            e.contains("short.csv:2") && e.contains("damper coefficient in N·s/m"),
            "{e}"
        );
        for p in [good, bad, twice, short] {
            let _ = std::fs::remove_file(p);
        }
    }
}
