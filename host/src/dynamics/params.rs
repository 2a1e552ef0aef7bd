//! What a dynamic model adds to the static one (thesis eq. 4–7): nodal masses, dampers beside
//! the springs, optional Rayleigh damping, and the time-stepping scheme. Checked here, before
//! anything is assembled, so bad input gets a message naming the quantity.

use std::fmt;
use std::str::FromStr;

use crate::model::{Grid, NodeField};

/// How a step advances u and v (see [`super`] for the equations).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Scheme {
    /// Backward (implicit) Euler, first order, L-stable: the default. It is what SOFA's
    /// default solver does and what the issue specifies exactly; its numerical damping kills
    /// the grid's highest, unresolved spring modes instead of letting them ring.
    #[default]
    BackwardEuler,
    /// Newmark average acceleration (the trapezoidal rule), second order, conserves the
    /// energy of an undamped model exactly; high modes are not damped at all.
    Trapezoidal,
}

impl Scheme {
    /// (c_B, c_K) in S = M + c_B·C + c_K·K: (h, h²) for backward Euler, (h/2, h²/4) for the
    /// trapezoidal rule.
    pub fn coefficients(self, h: f64) -> (f64, f64) {
        match self {
            Scheme::BackwardEuler => (h, h * h),
            Scheme::Trapezoidal => (0.5 * h, 0.25 * h * h),
        }
    }
}

impl fmt::Display for Scheme {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Scheme::BackwardEuler => "backward-euler",
            Scheme::Trapezoidal => "trapezoidal",
        })
    }
}

impl FromStr for Scheme {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "backward-euler" | "be" | "euler" => Ok(Scheme::BackwardEuler),
            "trapezoidal" | "newmark" | "tr" => Ok(Scheme::Trapezoidal),
            other => Err(format!(
                "unknown scheme '{other}': use backward-euler (first order, the default) or \
                 trapezoidal (Newmark average acceleration, second order)"
            )),
        }
    }
}

/// The damper coefficient β of the dampers beside the springs (N·s/m).
#[derive(Debug, Clone, PartialEq)]
pub enum Damping {
    /// Homogeneous, one β per displacement direction, like k.
    PerDirection([f64; 3]),
    /// Per node; a damper takes the mean of its two end nodes' β, like k̃. One B for x, y, z.
    Field(NodeField),
}

/// Everything a dynamic simulation needs besides the static model.
#[derive(Debug, Clone, PartialEq)]
pub struct DynamicsSpec {
    /// Lumped mass per node (kg): `background`, inclusions and per-node values as for the
    /// stiffness field. A uniform mass is `NodeField::uniform(m)`.
    pub mass: NodeField,
    pub damping: Damping,
    /// Rayleigh damping C = a·M + b·K added to the dampers' B.
    pub rayleigh: Option<[f64; 2]>,
    pub scheme: Scheme,
}

/// A scenario's `[dynamics]` table, checked (`crate::scenario::dynamics`): every key optional (flags and defaults fill in the rest).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DynamicsSettings {
    pub mass: Option<NodeField>,
    pub damping: Option<Damping>,
    pub rayleigh: Option<[f64; 2]>,
    pub scheme: Option<Scheme>,
}

/// Why a dynamic model or step is refused.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum DynamicsError {
    #[error("mass: {0} (the lumped mass of a node, kg, must be finite and greater than 0)")]
    Mass(String),
    #[error("damping: {0} (the damper coefficient β, N·s/m, must be finite and not negative; a field's values greater than 0)")]
    Damping(String),
    #[error("rayleigh = [{0}, {1}]: both coefficients must be finite and not negative")]
    Rayleigh(f64, f64),
    #[error("the time step h = {0} must be finite and greater than 0")]
    TimeStep(f64),
    #[error(
        "at h = {h}, S = M + h·B + h²·K cannot be represented in the target's 21-bit fixed \
         point: {reason}. Use a larger mass, a smaller h, or the quasi-static mode"
    )]
    Unrepresentable { h: f64, reason: String },
}

/// A field's value at every node, each finite and greater than 0. `NodeField`'s own
/// checks say "stiffness", so the values are checked here first to name the offender.
fn field_values(field: &NodeField, grid: Grid) -> Result<Vec<f64>, String> {
    let ok = |v: f64| v.is_finite() && v > 0.0;
    if !ok(field.background) {
        return Err(format!("the background value {}", field.background));
    }
    if let Some(i) = field.inclusions.iter().find(|i| !ok(i.k)) {
        return Err(format!("the inclusion at {:?} has value {}", i.center, i.k));
    }
    if let Some((node, v)) = field.nodes.iter().find(|(_, v)| !ok(*v)) {
        return Err(format!("node {node} has value {v}"));
    }
    field.values(grid).map_err(|e| e.to_string())
}

impl DynamicsSpec {
    /// A homogeneous model: mass m per node, β per direction, no Rayleigh term, backward Euler.
    pub fn uniform(mass: f64, damping: [f64; 3]) -> Self {
        Self {
            mass: NodeField::uniform(mass),
            damping: Damping::PerDirection(damping),
            rayleigh: None,
            scheme: Scheme::BackwardEuler,
        }
    }

    /// Every node's mass, checked.
    pub fn node_masses(&self, grid: Grid) -> Result<Vec<f64>, DynamicsError> {
        field_values(&self.mass, grid).map_err(DynamicsError::Mass)
    }

    /// Every node's β for a damper field, or `None` for per-direction damping (checked).
    pub fn node_damping(&self, grid: Grid) -> Result<Option<Vec<f64>>, DynamicsError> {
        match &self.damping {
            Damping::PerDirection(b) => {
                if let Some(v) = b.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
                    return Err(DynamicsError::Damping(format!("β = {v}")));
                }
                Ok(None)
            }
            // A damper field is positive everywhere: a per-node zero would leave springs
            // without dampers, which per-direction β = 0 already expresses.
            Damping::Field(f) => field_values(f, grid)
                .map(Some)
                .map_err(DynamicsError::Damping),
        }
    }

    /// The Rayleigh coefficients, checked.
    pub fn rayleigh(&self) -> Result<Option<[f64; 2]>, DynamicsError> {
        match self.rayleigh {
            Some([a, b]) if !(a.is_finite() && b.is_finite() && a >= 0.0 && b >= 0.0) => {
                Err(DynamicsError::Rayleigh(a, b))
            }
            r => Ok(r),
        }
    }

    /// One line for people.
    pub fn describe(&self) -> String {
        let mass = if self.mass.inclusions.is_empty() && self.mass.nodes.is_empty() {
            format!("mass {} kg per node", self.mass.background)
        } else {
            format!(
                "mass field (background {} kg, {} inclusion(s), {} node value(s))",
                self.mass.background,
                self.mass.inclusions.len(),
                self.mass.nodes.len()
            )
        };
        let damping = match &self.damping {
            Damping::PerDirection([x, y, z]) if x == y && y == z => format!("β = {x} N·s/m"),
            Damping::PerDirection([x, y, z]) => format!("β = ({x}, {y}, {z}) N·s/m"),
            Damping::Field(f) => format!("β field (background {} N·s/m)", f.background),
        };
        let rayleigh = match self.rayleigh {
            Some([a, b]) => format!(", Rayleigh C += {a}·M + {b}·K"),
            None => String::new(),
        };
        format!("{mass}, {damping}{rayleigh}, {}", self.scheme)
    }
}

/// h, checked.
pub fn check_time_step(h: f64) -> Result<f64, DynamicsError> {
    if h.is_finite() && h > 0.0 {
        Ok(h)
    } else {
        Err(DynamicsError::TimeStep(h))
    }
}
