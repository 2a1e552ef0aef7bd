//! One time step, up to the linear solve: the step matrices for an h, the right-hand side with
//! the constrained nodes' known velocities moved over, and the update of u and v once v₁ is
//! known. The solve itself is the caller's (the f64 reference in [`super::host`], the target in
//! [`super::target`]), so both run exactly the same scheme.

use super::params::{check_time_step, DynamicsError, Scheme};
use super::system::DynamicSystem;
use crate::model::boundary::eliminate_fixed_nodes;
use crate::model::{Axis, Csr};

/// Displacements and velocities of every node, per direction, at time t.
#[derive(Debug, Clone, PartialEq)]
pub struct State {
    pub t: f64,
    pub u: [Vec<f64>; 3],
    pub v: [Vec<f64>; 3],
}

impl State {
    /// At rest, undeformed, at t = 0.
    pub fn rest(n: usize) -> Self {
        Self {
            t: 0.0,
            u: [vec![0.0; n], vec![0.0; n], vec![0.0; n]],
            v: [vec![0.0; n], vec![0.0; n], vec![0.0; n]],
        }
    }
}

/// The loads at the step's start and end (t₀, t₁) and the prescribed displacements at t₁.
#[derive(Debug, Clone, Copy)]
pub struct Forcing<'a> {
    pub f0: [&'a [f64]; 3],
    pub f1: [&'a [f64]; 3],
    pub prescribed1: &'a [Option<[f64; 3]>],
}

/// S_d for one h and scheme, before and after elimination, and the directions grouped by
/// equal S (one fused target solve per group).
#[derive(Debug, Clone)]
pub struct StepMatrices {
    pub h: f64,
    pub scheme: Scheme,
    free: [Csr; 3],
    eliminated: [Csr; 3],
    /// Directions sharing one S, in order; one group when the tissue is isotropic.
    pub groups: Vec<Vec<Axis>>,
}

impl StepMatrices {
    pub fn new(system: &DynamicSystem, h: f64, scheme: Scheme) -> Result<Self, DynamicsError> {
        let h = check_time_step(h)?;
        let free = Axis::ALL.map(|d| system.free_step_matrix(d, h, scheme));
        let eliminated = free
            .clone()
            .map(|s| eliminate_fixed_nodes(&s, system.constrained()));
        let mut groups: Vec<Vec<Axis>> = Vec::new();
        for d in Axis::ALL {
            match groups
                .iter_mut()
                .find(|g| eliminated[g[0].position()] == eliminated[d.position()])
            {
                Some(g) => g.push(d),
                None => groups.push(vec![d]),
            }
        }
        Ok(Self {
            h,
            scheme,
            free,
            eliminated,
            groups,
        })
    }

    /// S_d as the target holds it (constrained rows and columns eliminated).
    pub fn matrix(&self, axis: Axis) -> &Csr {
        &self.eliminated[axis.position()]
    }

    /// S_d before elimination (its rows at constrained nodes move their velocities over).
    pub fn free(&self, axis: Axis) -> &Csr {
        &self.free[axis.position()]
    }
}

/// v₁ at a constrained node: 0 where fixed; where prescribed, the velocity that lands exactly
/// on the prescribed displacement at t₁ (backward Euler: Δu/h; trapezoidal: 2Δu/h − v₀).
fn known_velocity(m: &StepMatrices, state: &State, forcing: &Forcing, p: usize, j: usize) -> f64 {
    match forcing.prescribed1[j] {
        None => 0.0,
        Some(u1) => {
            let du = u1[p] - state.u[p][j];
            match m.scheme {
                Scheme::BackwardEuler => du / m.h,
                Scheme::Trapezoidal => 2.0 * du / m.h - state.v[p][j],
            }
        }
    }
}

/// The right-hand side of S_d·v₁ = b for direction `axis`:
///
/// - backward Euler: b = M·v₀ + h·(f₁ − K·u₀);
/// - trapezoidal: b = M·v₀ − (h/2·C + h²/4·K)·v₀ + h·((f₀ + f₁)/2 − K·u₀);
///
/// then, as for prescribed displacements in the static model, each constrained node j's known
/// v₁ⱼ moves over: b_i −= S_ij·v₁ⱼ for free i, and b_j = S_jj·v₁ⱼ.
pub fn rhs(
    system: &DynamicSystem,
    m: &StepMatrices,
    state: &State,
    forcing: &Forcing,
    axis: Axis,
) -> Vec<f64> {
    let p = axis.position();
    let (h, u0, v0) = (m.h, &state.u[p], &state.v[p]);
    let ku = system.stiffness(axis).mul_vec(u0);
    let mut b: Vec<f64> = (0..system.n())
        .map(|i| {
            let f = match m.scheme {
                Scheme::BackwardEuler => forcing.f1[p][i],
                Scheme::Trapezoidal => 0.5 * (forcing.f0[p][i] + forcing.f1[p][i]),
            };
            system.mass()[i] * v0[i] + h * (f - ku[i])
        })
        .collect();
    if m.scheme == Scheme::Trapezoidal {
        // (S − M)·v₀ = (h/2·C + h²/4·K)·v₀.
        let sv = m.free[p].mul_vec(v0);
        for (i, b) in b.iter_mut().enumerate() {
            *b -= sv[i] - system.mass()[i] * v0[i];
        }
    }
    let constrained = system.constrained();
    for j in (0..system.n()).filter(|&j| constrained[j]) {
        let vj = known_velocity(m, state, forcing, p, j);
        let (cols, vals) = m.free[p].row(j);
        // S is symmetric: column j is row j.
        for (&i, &sij) in cols.iter().zip(vals) {
            if i == j {
                b[j] = sij * vj;
            } else if !constrained[i] {
                b[i] -= sij * vj;
            }
        }
    }
    b
}

/// The state at t₁ = t₀ + h from v₁ (one vector per direction): backward Euler
/// u₁ = u₀ + h·v₁, trapezoidal u₁ = u₀ + h·(v₀ + v₁)/2; prescribed nodes land exactly on
/// their value (the update reaches it up to rounding) and fixed nodes stay at rest.
pub fn advance(
    system: &DynamicSystem,
    m: &StepMatrices,
    state: &State,
    mut v1: [Vec<f64>; 3],
    forcing: &Forcing,
) -> State {
    let h = m.h;
    for (i, _) in system.constrained().iter().enumerate().filter(|(_, &c)| c) {
        if forcing.prescribed1[i].is_none() {
            for v in &mut v1 {
                v[i] = 0.0;
            }
        }
    }
    let u = [0, 1, 2].map(|p| {
        let mut u: Vec<f64> = (0..v1[p].len())
            .map(|i| match m.scheme {
                Scheme::BackwardEuler => state.u[p][i] + h * v1[p][i],
                Scheme::Trapezoidal => state.u[p][i] + 0.5 * h * (state.v[p][i] + v1[p][i]),
            })
            .collect();
        for (i, pre) in forcing.prescribed1.iter().enumerate() {
            if let Some(value) = pre {
                u[i] = value[p];
            }
        }
        u
    });
    State {
        t: state.t + h,
        u,
        v: v1,
    }
}

/// A model's loads and prescribed displacements at one time: what [`Forcing`] borrows.
#[derive(Debug, Clone, PartialEq)]
pub struct Loads {
    pub f: [Vec<f64>; 3],
    pub prescribed: Vec<Option<[f64; 3]>>,
}

impl Loads {
    pub fn of(model: &crate::model::Model) -> Self {
        Self {
            f: Axis::ALL.map(|d| model.load(d).to_vec()),
            prescribed: model.prescribed().to_vec(),
        }
    }

    /// The forcing of a step from `self` (at t₀) to `end` (at t₁).
    pub fn to<'a>(&'a self, end: &'a Loads) -> Forcing<'a> {
        Forcing {
            f0: [&self.f[0], &self.f[1], &self.f[2]],
            f1: [&end.f[0], &end.f[1], &end.f[2]],
            prescribed1: &end.prescribed,
        }
    }
}
