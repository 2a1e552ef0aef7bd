//! The `[dynamics]` table of a scenario file (issue 14; see [`crate::dynamics`]). It is used
//! when `[simulation] dynamic = true` or `deform simulate --dynamic`.
//!
//! ```toml
//! [dynamics]
//! mass = 0.05                  # kg per node; or a field:
//! # mass = { background = 0.05, inclusion = [{ center = [5, 5, 5], radius = 2, value = 0.2 }], field = "mass.csv" }
//! damping = 0.02               # β, N·s/m; or [BX, BY, BZ], or a field like mass
//! rayleigh = [0.0, 0.01]       # optional: C += a·M + b·K
//! scheme = "backward-euler"    # or "trapezoidal"
//! ```

use serde::Deserialize;
use toml::Spanned;

use super::field::{FieldParts, InclusionAt, Quantity, DAMPING, MASS};
use super::{Ctx, ScenarioError};
use crate::dynamics::Damping;
pub use crate::dynamics::DynamicsSettings;
use crate::model::{Grid, NodeField};

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct DynamicsToml {
    mass: Option<Spanned<QuantityToml>>,
    damping: Option<Spanned<QuantityToml>>,
    rayleigh: Option<Spanned<[f64; 2]>>,
    scheme: Option<Spanned<String>>,
}

/// A number, three numbers (one per direction) or a per-node field.
#[derive(Debug, Deserialize)]
#[serde(untagged)]
enum QuantityToml {
    One(f64),
    Three([f64; 3]),
    Field(FieldToml),
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct FieldToml {
    background: f64,
    #[serde(default)]
    inclusion: Vec<InclusionToml>,
    field: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct InclusionToml {
    center: [f64; 3],
    radius: f64,
    value: f64,
}

fn positive(v: f64) -> bool {
    v.is_finite() && v > 0.0
}

/// A `{ background, inclusion, field }` table, through the one node-field parser.
fn field(
    cx: &Ctx<'_>,
    grid: Grid,
    f: &FieldToml,
    span: std::ops::Range<usize>,
    key: &str,
    quantity: Quantity,
) -> Result<NodeField, ScenarioError> {
    FieldParts {
        key,
        subkeys: false,
        quantity,
        background: (f.background, span.clone()),
        inclusions: f
            .inclusion
            .iter()
            .map(|inc| InclusionAt {
                center: inc.center,
                radius: inc.radius,
                value: inc.value,
                span: span.clone(),
            })
            .collect(),
        csv: f.field.as_deref().map(|csv| (csv, span.clone())),
    }
    .resolve(cx, grid)
}

pub(super) fn resolve_dynamics(
    cx: &Ctx<'_>,
    grid: Grid,
    d: &DynamicsToml,
) -> Result<DynamicsSettings, ScenarioError> {
    let mut out = DynamicsSettings::default();
    if let Some(m) = &d.mass {
        out.mass = Some(match m.get_ref() {
            QuantityToml::One(v) if positive(*v) => NodeField::uniform(*v),
            QuantityToml::Field(f) => field(cx, grid, f, m.span(), "dynamics.mass", MASS)?,
            QuantityToml::One(_) => {
                return Err(cx.err(
                    m.span(),
                    "dynamics.mass",
                    "the mass per node (kg) must be finite and greater than 0",
                ))
            }
            QuantityToml::Three(_) => {
                return Err(cx.err(
                    m.span(),
                    "dynamics.mass",
                    "a mass is one number per node, not one per direction",
                ))
            }
        });
    }
    if let Some(b) = &d.damping {
        let bad = || {
            cx.err(
                b.span(),
                "dynamics.damping",
                "the damper coefficient β (N·s/m) must be finite and greater than 0",
            )
        };
        out.damping = Some(match b.get_ref() {
            QuantityToml::One(v) if positive(*v) => Damping::PerDirection([*v; 3]),
            QuantityToml::Three(v) if v.iter().all(|x| positive(*x)) => Damping::PerDirection(*v),
            QuantityToml::Field(f) => {
                Damping::Field(field(cx, grid, f, b.span(), "dynamics.damping", DAMPING)?)
            }
            _ => return Err(bad()),
        });
    }
    if let Some(r) = &d.rayleigh {
        let [a, b] = *r.get_ref();
        if !(a.is_finite() && b.is_finite() && a >= 0.0 && b >= 0.0) {
            return Err(cx.err(
                r.span(),
                "dynamics.rayleigh",
                "[a, b] must both be finite and not negative",
            ));
        }
        out.rayleigh = Some([a, b]);
    }
    if let Some(s) = &d.scheme {
        out.scheme = Some(
            s.get_ref()
                .parse()
                .map_err(|e: String| cx.err(s.span(), "dynamics.scheme", e))?,
        );
    }
    Ok(out)
}
