//! One k̃ per spring: non-homogeneous tissue (thesis 3.3, eq. 54).
//!
//! At a free node p, f_p^d = Σ_s k̃_s·(l̃_p^d − l̃_q^d): linear in the spring stiffnesses with
//! coefficients taken from the observed displacements. Least squares over nodes, directions
//! and sets gives the normal system H·k = b, H = Σ g·gᵀ (eq. 54). H couples two springs only
//! when they meet at a free node, so it is as sparse as the spring adjacency; with the springs
//! in node-major order ([`super::Network`]) its band is about 3·NX·NY for model A, and it is
//! built, encoded as instruction words and solved on the target like any SPD system (symmetric
//! diagonal scaling first: every diagonal becomes 1, which suits the fixed-point format).
//!
//! Unknowns are the springs with at least one free end; a spring between two fixed or
//! prescribed nodes acts on nothing the data show and is left out. The springs that join one
//! free node to its constrained neighbours enter only that node's equation, each times
//! (l̃_p − known l̃_q): with the neighbours fixed that is the same l̃_p for all of them, so the
//! data determine only their sum. They share one unknown (an "anchor" of that node), which
//! assumes them equal; in model A with a fixed face each free node has at most one anyway.
//!
//! Repeated sets under the same loads are pooled first (their displacements averaged per
//! direction): the normal equations are quadratic in the displacements, so averaging S
//! replicates divides the noise-induced bias of H by S, as in the homogeneous case.

use std::collections::HashMap;

use serde::Serialize;

use super::regularise::Regularisation;
use super::solver::{SolveCount, SpdSolver};
use super::{EstimateError, Network, Observations};
use crate::link::Port;
use crate::model::sparse::CsrBuilder;
use crate::model::Csr;

/// One spring's estimate.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SpringValue {
    pub a: [usize; 3],
    pub b: [usize; 3],
    pub k: f64,
}

/// Where the stiffest region of a node map is.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct StiffRegion {
    /// Node-index coordinates of its stiffness-weighted centre.
    pub centre: [f64; 3],
    /// Nodes at or above the threshold.
    pub nodes: usize,
    /// Halfway between the median and the maximum of the map.
    pub threshold: f64,
    pub median: f64,
    pub max: f64,
}

/// The per-spring estimate and what it took.
#[derive(Debug, Clone, Serialize)]
pub struct SpringFieldEstimate {
    /// Unknowns (springs between free nodes, plus one anchor per free node next to constrained
    /// ones).
    pub unknowns: usize,
    /// Scalar equations after pooling (free nodes × pooled fields that move).
    pub equations: usize,
    /// Displacement fields after pooling replicate sets.
    pub fields: usize,
    /// Nonzeros of the normal matrix H and its half-bandwidth.
    pub normal_nnz: usize,
    pub normal_bandwidth: usize,
    /// The homogeneous equation-error estimate of the pooled data (the Tikhonov prior).
    pub prior_k: f64,
    pub regularisation: Vec<String>,
    /// ‖f − G·k‖₂ / ‖f‖₂ on the pooled data.
    pub relative_residual: f64,
    pub solves: SolveCount,
    pub min_k: f64,
    pub max_k: f64,
    pub stiff_region: StiffRegion,
    pub springs: Vec<SpringValue>,
    /// Per node: the mean of its springs' estimates (the map written as VTK).
    pub node_stiffness: Vec<f64>,
}

/// A displacement field with its loads, the mean of `weight` replicate sets.
struct Field {
    u: Vec<f64>,
    f: Vec<f64>,
    weight: f64,
}

/// Averages the displacements of sets with identical loads, per direction.
fn pooled_fields(net: &Network, obs: &Observations) -> Vec<Field> {
    let mut index: HashMap<(usize, Vec<u64>), usize> = HashMap::new();
    let mut fields: Vec<Field> = Vec::new();
    for set in &obs.sets {
        let u = net.effective_displacements(set);
        for d in 0..3 {
            let key = (d, set.f[d].iter().map(|v| v.to_bits()).collect());
            let slot = *index.entry(key).or_insert_with(|| {
                fields.push(Field {
                    u: vec![0.0; u[d].len()],
                    f: set.f[d].clone(),
                    weight: 0.0,
                });
                fields.len() - 1
            });
            let field = &mut fields[slot];
            field.weight += 1.0;
            for (acc, v) in field.u.iter_mut().zip(&u[d]) {
                *acc += v;
            }
        }
    }
    for field in &mut fields {
        for v in &mut field.u {
            *v /= field.weight;
        }
    }
    fields
}

/// The sparsity pattern of H (springs meeting at a node) and, per node, where each pair of its
/// unknowns lands in the value array.
struct Pattern {
    row_ptr: Vec<usize>,
    col: Vec<usize>,
    /// Per node: its unknowns, and the value positions of every (i, j) pair, row-major.
    node_unknowns: Vec<Vec<usize>>,
    node_slots: Vec<Vec<usize>>,
}

impl Pattern {
    /// Where row `a`'s diagonal sits in the values.
    fn diagonal_slot(&self, a: usize) -> usize {
        self.row_ptr[a]
            + self.col[self.row_ptr[a]..self.row_ptr[a + 1]]
                .binary_search(&a)
                .expect("diagonal")
    }
}

fn pattern(net: &Network, unknown_of: &[Option<usize>], m: usize) -> Pattern {
    let node_unknowns: Vec<Vec<usize>> = (0..net.n())
        .map(|p| {
            let mut u: Vec<usize> = net
                .incident(p)
                .iter()
                .filter_map(|&s| unknown_of[s])
                .collect();
            u.sort_unstable();
            u.dedup();
            u
        })
        .collect();
    let mut rows: Vec<Vec<usize>> = vec![Vec::new(); m];
    for unknowns in &node_unknowns {
        for &a in unknowns {
            rows[a].extend_from_slice(unknowns);
        }
    }
    let mut row_ptr = vec![0];
    let mut col = Vec::new();
    for row in &mut rows {
        row.sort_unstable();
        row.dedup();
        col.extend_from_slice(row);
        row_ptr.push(col.len());
    }
    let node_slots = node_unknowns
        .iter()
        .map(|unknowns| {
            let mut slots = Vec::with_capacity(unknowns.len() * unknowns.len());
            for &a in unknowns {
                let cols = &col[row_ptr[a]..row_ptr[a + 1]];
                for b in unknowns {
                    let offset = cols.binary_search(b).expect("pattern holds every pair");
                    slots.push(row_ptr[a] + offset);
                }
            }
            slots
        })
        .collect();
    Pattern {
        row_ptr,
        col,
        node_unknowns,
        node_slots,
    }
}

/// The per-node map and its stiffest region.
fn node_map(net: &Network, unknown_of: &[Option<usize>], k: &[f64], fallback: f64) -> Vec<f64> {
    (0..net.n())
        .map(|p| {
            let values: Vec<f64> = net
                .incident(p)
                .iter()
                .filter_map(|&s| unknown_of[s].map(|a| k[a]))
                .collect();
            if values.is_empty() {
                fallback
            } else {
                values.iter().sum::<f64>() / values.len() as f64
            }
        })
        .collect()
}

/// The stiffness-weighted centre of the nodes at or above halfway between the median and the
/// maximum of `map`.
pub fn stiff_region(net: &Network, map: &[f64]) -> StiffRegion {
    let mut sorted = map.to_vec();
    sorted.sort_by(f64::total_cmp);
    let median = sorted[sorted.len() / 2];
    let max = *sorted.last().expect("a grid has nodes");
    let threshold = median + 0.5 * (max - median);
    let (mut centre, mut total, mut nodes) = ([0.0; 3], 0.0, 0);
    for (p, &v) in map.iter().enumerate() {
        if v >= threshold {
            let weight = (v - median).max(f64::MIN_POSITIVE);
            let node = net.node(p);
            for (c, x) in centre.iter_mut().zip([node.i, node.j, node.k]) {
                *c += weight * x as f64;
            }
            total += weight;
            nodes += 1;
        }
    }
    StiffRegion {
        centre: centre.map(|c| c / total),
        nodes,
        threshold,
        median,
        max,
    }
}

/// Which unknown each spring is: a spring between two free nodes is its own; the springs
/// from one free node to constrained ones (its anchors) share one.
struct Unknowns {
    /// Per spring, its unknown (`None`: both ends constrained).
    of: Vec<Option<usize>>,
    /// Per unknown, its springs.
    springs: Vec<Vec<usize>>,
}

impl Unknowns {
    fn of(net: &Network) -> Self {
        let springs = net.springs();
        let mut of = vec![None; springs.len()];
        let mut springs_of: Vec<Vec<usize>> = Vec::new();
        let mut anchor_of: HashMap<usize, usize> = HashMap::new();
        for (s, &(p, q)) in springs.iter().enumerate() {
            let unknown = match (net.is_constrained(p), net.is_constrained(q)) {
                (true, true) => continue,
                (false, false) => {
                    springs_of.push(Vec::new());
                    springs_of.len() - 1
                }
                (true, false) | (false, true) => {
                    let free = if net.is_constrained(p) { q } else { p };
                    *anchor_of.entry(free).or_insert_with(|| {
                        springs_of.push(Vec::new());
                        springs_of.len() - 1
                    })
                }
            };
            of[s] = Some(unknown);
            springs_of[unknown].push(s);
        }
        Self {
            of,
            springs: springs_of,
        }
    }

    fn count(&self) -> usize {
        self.springs.len()
    }
}

/// The normal equations H·k = b of the pooled fields, on `pat`, and the sums of the
/// homogeneous fit (Σ w·f·g, Σ w·g², Σ w·f²) that give the prior k and the misfit's scale.
struct Normal {
    h: Vec<f64>,
    b: Vec<f64>,
    fg: f64,
    gg: f64,
    ff: f64,
}

impl Normal {
    fn assemble(net: &Network, fields: &[Field], unknowns: &Unknowns, pat: &Pattern) -> Self {
        let mut out = Normal {
            h: vec![0.0; pat.col.len()],
            b: vec![0.0; unknowns.count()],
            fg: 0.0,
            gg: 0.0,
            ff: 0.0,
        };
        let mut coefficients = Vec::new();
        for field in fields {
            for p in net.free_nodes() {
                let node_unknowns = &pat.node_unknowns[p];
                coefficients.clear();
                coefficients.resize(node_unknowns.len(), 0.0);
                for &s in net.incident(p) {
                    let a = unknowns.of[s].expect("a spring at a free node is an unknown");
                    let slot = node_unknowns
                        .binary_search(&a)
                        .expect("the node's unknowns");
                    coefficients[slot] += field.u[p] - field.u[net.other_end(s, p)];
                }
                let (w, f) = (field.weight, field.f[p]);
                let slots = &pat.node_slots[p];
                for (i, &ci) in coefficients.iter().enumerate() {
                    out.b[node_unknowns[i]] += w * ci * f;
                    for (j, &cj) in coefficients.iter().enumerate() {
                        out.h[slots[i * node_unknowns.len() + j]] += w * ci * cj;
                    }
                }
                let g: f64 = coefficients.iter().sum();
                out.fg += w * f * g;
                out.gg += w * g * g;
                out.ff += w * f * f;
            }
        }
        out
    }

    /// The homogeneous k the Tikhonov term pulls towards (and unknowns without data take).
    fn prior_k(&self) -> f64 {
        if self.gg > 0.0 {
            self.fg / self.gg
        } else {
            1.0
        }
    }

    /// Adds the regularisation terms, each weighted relative to the data's mean diagonal.
    fn regularise(&mut self, pat: &Pattern, regularisation: &[Regularisation]) {
        let m = self.b.len();
        let prior_k = self.prior_k();
        let positive: Vec<f64> = (0..m)
            .map(|a| self.h[pat.diagonal_slot(a)])
            .filter(|&d| d > 0.0)
            .collect();
        let mean_diagonal = if positive.is_empty() {
            1.0
        } else {
            positive.iter().sum::<f64>() / positive.len() as f64
        };
        for r in regularisation {
            let lambda = r.weight() * mean_diagonal;
            match r {
                Regularisation::Tikhonov(_) => {
                    for a in 0..m {
                        self.h[pat.diagonal_slot(a)] += lambda;
                        self.b[a] += lambda * prior_k;
                    }
                }
                Regularisation::Smooth(_) => {
                    for (unknowns, slots) in pat.node_unknowns.iter().zip(&pat.node_slots) {
                        let len = unknowns.len();
                        for i in 0..len {
                            for j in (0..len).filter(|&j| j != i) {
                                self.h[slots[i * len + i]] += lambda;
                                self.h[slots[i * len + j]] -= lambda;
                            }
                        }
                    }
                }
            }
        }
    }

    /// Solves H·k = b on `solver` with symmetric diagonal scaling (unit diagonal, |entries|
    /// ≤ 1); k, and H as scaled (its size for the report).
    fn solve<P: Port>(
        &self,
        pat: &Pattern,
        diagonal: &[f64],
        solver: &mut SpdSolver<'_, P>,
        solves: &mut SolveCount,
    ) -> Result<(Vec<f64>, Csr), EstimateError> {
        let m = self.b.len();
        let scale: Vec<f64> = diagonal.iter().map(|d| 1.0 / d.sqrt()).collect();
        let mut builder = CsrBuilder::new(m, self.h.len());
        for a in 0..m {
            let range = pat.row_ptr[a]..pat.row_ptr[a + 1];
            builder
                .push_row(
                    pat.col[range.clone()]
                        .iter()
                        .zip(&self.h[range])
                        .map(|(&c, &v)| (c, v * scale[a] * scale[c])),
                )
                .expect("columns are inside the matrix");
        }
        let scaled: Csr = builder.finish().expect("one row per unknown");
        let rhs: Vec<f64> = self.b.iter().zip(&scale).map(|(b, s)| b * s).collect();
        let y = solver
            .solve_all(&scaled, &[rhs], solves)
            .map_err(|e| match e {
                super::solver::SpdSolveError::NotConverged { residual, .. } => {
                    EstimateError::Singular {
                        estimator: "spring-field",
                        why: format!(
                            "CG stalled at a relative residual of {residual:.3e}: the springs are not all determined by \
                             these observations; observe under more load cases, or add --regularise"
                        ),
                    }
                }
                other => other.into(),
            })?
            .pop()
            .expect("one right-hand side");
        Ok((y.iter().zip(&scale).map(|(y, s)| y * s).collect(), scaled))
    }
}

/// Refuses a system the observations do not determine: fewer equations than unknowns without
/// regularisation, or an unknown spring that never stretches. The equations and the diagonal
/// otherwise.
fn determined(
    net: &Network,
    fields: &[Field],
    unknowns: &Unknowns,
    diagonal: &[f64],
    regularised: bool,
) -> Result<usize, EstimateError> {
    let m = unknowns.count();
    // Fields that move at all: each gives one equation per free node.
    let moving = fields
        .iter()
        .filter(|field| net.free_nodes().any(|p| field.u[p] != 0.0))
        .count();
    let equations = moving * net.free_nodes().count();
    if !regularised && equations < m {
        return Err(EstimateError::Singular {
            estimator: "spring-field",
            why: format!(
                "{equations} equations ({moving} moving displacement field(s) × free nodes) for {m} unknown springs; \
                 observe under more load cases (each set gives one field per loaded direction), or add --regularise"
            ),
        });
    }
    let idle: Vec<usize> = (0..m).filter(|&a| diagonal[a] <= 0.0).collect();
    if let Some(&a) = idle.first() {
        let (p, q) = net.springs()[unknowns.springs[a][0]];
        return Err(EstimateError::Singular {
            estimator: "spring-field",
            why: format!(
                "{} of {m} unknown springs never stretch in any observation (the first joins nodes {} and {}), \
                 so nothing determines them; observe under more load cases, or add --regularise tikhonov:W or smooth:W",
                idle.len(),
                net.node(p),
                net.node(q)
            ),
        });
    }
    Ok(equations)
}

/// Σ w·(f − K(k)·u)² over the pooled fields: the data misfit of the estimate.
fn misfit(net: &Network, fields: &[Field], unknowns: &Unknowns, k: &[f64]) -> f64 {
    let mut rss = 0.0;
    for field in fields {
        for p in net.free_nodes() {
            let predicted: f64 = net
                .incident(p)
                .iter()
                .map(|&s| {
                    let a = unknowns.of[s].expect("a spring at a free node is an unknown");
                    k[a] * (field.u[p] - field.u[net.other_end(s, p)])
                })
                .sum();
            rss += field.weight * (field.f[p] - predicted).powi(2);
        }
    }
    rss
}

/// One k̃ per spring by least squares (eq. 54), optionally regularised, solved on `solver`.
pub fn estimate<P: Port>(
    net: &Network,
    obs: &Observations,
    regularisation: &[Regularisation],
    solver: &mut SpdSolver<'_, P>,
) -> Result<SpringFieldEstimate, EstimateError> {
    if obs.sets.is_empty() {
        return Err(EstimateError::NoSets);
    }
    let unknowns = Unknowns::of(net);
    let m = unknowns.count();
    let pat = pattern(net, &unknowns.of, m);
    let fields = pooled_fields(net, obs);
    let mut normal = Normal::assemble(net, &fields, &unknowns, &pat);
    let prior_k = normal.prior_k();
    normal.regularise(&pat, regularisation);
    let diagonal: Vec<f64> = (0..m).map(|a| normal.h[pat.diagonal_slot(a)]).collect();
    let equations = determined(
        net,
        &fields,
        &unknowns,
        &diagonal,
        !regularisation.is_empty(),
    )?;
    let mut solves = SolveCount::default();
    let (k, scaled) = normal.solve(&pat, &diagonal, solver, &mut solves)?;
    let rss = misfit(net, &fields, &unknowns, &k);
    let relative_residual = if normal.ff > 0.0 {
        (rss / normal.ff).sqrt()
    } else {
        0.0
    };
    super::ensure_finite(
        "per-spring",
        &[
            ("the relative residual", relative_residual),
            (
                "a spring's k",
                k.iter().copied().find(|v| !v.is_finite()).unwrap_or(0.0),
            ),
        ],
    )?;
    let node_stiffness = node_map(net, &unknowns.of, &k, prior_k);
    let stiff_region = stiff_region(net, &node_stiffness);
    let node_coords = |p: usize| {
        let n = net.node(p);
        [n.i, n.j, n.k]
    };
    Ok(SpringFieldEstimate {
        unknowns: m,
        equations,
        fields: fields.len(),
        normal_nnz: scaled.nnz(),
        normal_bandwidth: scaled.bandwidth(),
        prior_k,
        regularisation: regularisation.iter().map(|r| r.to_string()).collect(),
        relative_residual,
        solves,
        min_k: k.iter().copied().fold(f64::INFINITY, f64::min),
        max_k: k.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        stiff_region,
        springs: net
            .springs()
            .iter()
            .zip(&unknowns.of)
            .filter_map(|(&(p, q), a)| {
                a.map(|a| SpringValue {
                    a: node_coords(p),
                    b: node_coords(q),
                    k: k[a],
                })
            })
            .collect(),
        node_stiffness,
    })
}
