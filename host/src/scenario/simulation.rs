//! The `[simulation]` table of a scenario file: what `deform simulate` reads. `deform solve`
//! only evaluates its schedules at the final time (see [`super`]).
//!
//! ```toml
//! [simulation]
//! steps = 50          # time steps
//! dt = 0.02           # seconds per step; the run covers t = 0 … steps·dt
//! dynamic = true      # optional: masses and dampers of [dynamics], loads without a ramp
//!
//! [[simulation.displace]]            # a prescribed displacement over time
//! node = [5, 5, 9]
//! keyframes = [[0.0, 0, 0, 0], [1.0, 0, 0, -2]]   # [t, ux, uy, uz], piecewise linear
//!
//! [[simulation.load]]                # a point load over time
//! node = [0, 5, 5]
//! keyframes = [[0.0, 0, 0, 0], [0.5, 1, 0, 0]]    # [t, fx, fy, fz]
//!
//! [simulation.nonlinear]             # optional, displacement-dependent springs
//! alpha = [1.0, 0.0, 0.5]
//! ```

use serde::Deserialize;

use crate::model::{ModelSpec, Node};

/// One keyframe: `[t, x, y, z]`.
pub type Keyframe = [f64; 4];

/// The value of a piecewise-linear schedule at time `t`: linear between neighbouring
/// keyframes, held at the first keyframe's value before it and at the last one's after it.
/// Keyframes must be sorted by time (the scenario loader checks this); two keyframes at the same
/// time make a step, and the later one holds from that time on. An empty schedule is zero.
pub fn value_at(keyframes: &[Keyframe], t: f64) -> [f64; 3] {
    let xyz = |k: &Keyframe| [k[1], k[2], k[3]];
    let Some(first) = keyframes.first() else {
        return [0.0; 3];
    };
    if t < first[0] {
        return xyz(first);
    }
    // The last keyframe at or before t.
    let at = keyframes.partition_point(|k| k[0] <= t) - 1;
    let a = &keyframes[at];
    match keyframes.get(at + 1) {
        None => xyz(a),
        Some(b) => {
            let s = (t - a[0]) / (b[0] - a[0]);
            [0, 1, 2].map(|d| a[d + 1] + s * (b[d + 1] - a[d + 1]))
        }
    }
}

/// `[simulation]`, resolved: nodes checked against the grid, keyframes sorted and finite.
#[derive(Debug, Clone, PartialEq)]
pub struct Simulation {
    pub steps: u32,
    /// Seconds per step.
    pub dt: f64,
    pub displace: Vec<NodeSchedule>,
    pub load: Vec<NodeSchedule>,
    pub nonlinear: Option<Nonlinear>,
    /// Elastodynamics (masses and dampers, `[dynamics]`) instead of quasi-static steps.
    pub dynamic: bool,
}

impl Simulation {
    /// The time of the last step, steps·dt.
    pub fn end_time(&self) -> f64 {
        self.steps as f64 * self.dt
    }

    /// The file line of the schedule at `node`, if a file gave one.
    pub fn line_of(&self, node: Node) -> Option<usize> {
        self.displace
            .iter()
            .chain(&self.load)
            .find(|s| s.node == node && s.line > 0)
            .map(|s| s.line)
    }

    /// Puts the schedules' values at [`Simulation::end_time`] into `spec`, the static state
    /// `deform solve` solves: a scheduled displacement replaces a static one at the same node,
    /// scheduled loads add to the static ones.
    pub fn apply_at_end(&self, spec: &mut ModelSpec) {
        let t = self.end_time();
        for s in &self.displace {
            let u = s.value_at(t);
            spec.prescribed.retain(|d| d.node != s.node);
            spec.prescribed
                .push(crate::model::PrescribedDisplacement { node: s.node, u });
        }
        for s in &self.load {
            spec.loads.push(crate::model::PointLoad {
                node: s.node,
                force: s.value_at(t),
            });
        }
    }

    /// The model at time `t`, from `final_spec`, the static model a scenario gives (the
    /// schedules evaluated at [`Simulation::end_time`], see [`super`]) with any command-line
    /// flags merged over it: each scheduled displacement and point load that is still there
    /// with its final value takes its value at `t` instead. One the flags replaced (a --displace
    /// or --load list given) is left as the flags say. The prescribed nodes are the same at
    /// every t, so the model's matrix is too.
    pub fn spec_at(&self, final_spec: &ModelSpec, t: f64) -> ModelSpec {
        let end = self.end_time();
        let mut spec = final_spec.clone();
        for s in &self.displace {
            let at_end = s.value_at(end);
            if let Some(d) = spec
                .prescribed
                .iter_mut()
                .find(|d| d.node == s.node && d.u == at_end)
            {
                d.u = s.value_at(t);
            }
        }
        // The scenario appends the scheduled loads after the static ones, in order.
        let mut tail = spec.loads.len();
        for s in self.load.iter().rev() {
            let at_end = s.value_at(end);
            if let Some(i) = spec.loads[..tail]
                .iter()
                .rposition(|l| l.node == s.node && l.force == at_end)
            {
                spec.loads[i].force = s.value_at(t);
                tail = i;
            }
        }
        spec
    }
}

/// A displacement or load of one node over time.
#[derive(Debug, Clone, PartialEq)]
pub struct NodeSchedule {
    pub node: Node,
    pub keyframes: Vec<Keyframe>,
    /// The scenario file's line that names the node (0: not from a file), for messages.
    pub line: usize,
}

impl NodeSchedule {
    pub fn value_at(&self, t: f64) -> [f64; 3] {
        value_at(&self.keyframes, t)
    }
}

/// `[simulation.nonlinear]`: coefficients of displacement-dependent springs (their meaning is
/// `deform simulate`'s to define).
#[derive(Debug, Clone, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Nonlinear {
    pub alpha: [f64; 3],
}

/// `[simulation]` as written in the file (spans kept for error messages).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SimulationToml {
    pub steps: toml::Spanned<u32>,
    pub dt: toml::Spanned<f64>,
    #[serde(default)]
    pub displace: Vec<ScheduleToml>,
    #[serde(default)]
    pub load: Vec<ScheduleToml>,
    pub nonlinear: Option<Nonlinear>,
    pub dynamic: Option<bool>,
}

/// `[[simulation.displace]]` / `[[simulation.load]]` as written in the file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScheduleToml {
    pub node: toml::Spanned<[usize; 3]>,
    pub keyframes: toml::Spanned<Vec<Keyframe>>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn piecewise_linear_and_held_outside() {
        let k = [
            [0.0, 0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0, -2.0],
            [2.0, 1.0, 0.0, -2.0],
        ];
        assert_eq!(value_at(&k, -1.0), [0.0, 0.0, 0.0]);
        assert_eq!(value_at(&k, 0.0), [0.0, 0.0, 0.0]);
        assert_eq!(value_at(&k, 0.25), [0.0, 0.0, -0.5]);
        assert_eq!(value_at(&k, 1.0), [0.0, 0.0, -2.0]);
        assert_eq!(value_at(&k, 1.5), [0.5, 0.0, -2.0]);
        assert_eq!(value_at(&k, 2.0), [1.0, 0.0, -2.0]);
        assert_eq!(value_at(&k, 7.0), [1.0, 0.0, -2.0]);
    }

    #[test]
    fn single_empty_and_step_schedules() {
        assert_eq!(value_at(&[], 1.0), [0.0; 3]);
        let one = [[0.5, 1.0, 2.0, 3.0]];
        assert_eq!(value_at(&one, 0.0), [1.0, 2.0, 3.0]);
        assert_eq!(value_at(&one, 9.0), [1.0, 2.0, 3.0]);
        let step = [
            [0.0, 0.0, 0.0, 0.0],
            [1.0, 1.0, 0.0, 0.0],
            [1.0, 5.0, 0.0, 0.0],
        ];
        assert_eq!(value_at(&step, 0.5), [0.5, 0.0, 0.0]);
        assert_eq!(value_at(&step, 1.0), [5.0, 0.0, 0.0]);
        assert_eq!(value_at(&step, 2.0), [5.0, 0.0, 0.0]);
    }

    #[test]
    fn spec_at_follows_the_keyframes_and_leaves_static_loads() {
        use crate::model::{PointLoad, PrescribedDisplacement};
        let tip = Node::new(1, 1, 1);
        let side = Node::new(0, 1, 1);
        let sim = Simulation {
            steps: 4,
            dt: 0.5,
            displace: vec![NodeSchedule {
                node: tip,
                keyframes: vec![[0.0, 0.0, 0.0, 0.0], [2.0, 0.0, 0.0, 2.0]],
                line: 0,
            }],
            load: vec![NodeSchedule {
                node: side,
                keyframes: vec![[0.0, 0.0, 0.0, 0.0], [1.0, 4.0, 0.0, 0.0]],
                line: 0,
            }],
            nonlinear: None,
            dynamic: false,
        };
        let static_load = PointLoad {
            node: side,
            force: [1.0, 0.0, 0.0],
        };
        // What the scenario loader makes of it: the schedules at t = 2.
        let mut spec = ModelSpec::thesis_example();
        spec.loads = vec![
            static_load,
            PointLoad {
                node: side,
                force: [4.0, 0.0, 0.0],
            },
        ];
        spec.prescribed = vec![PrescribedDisplacement {
            node: tip,
            u: [0.0, 0.0, 2.0],
        }];
        let at = sim.spec_at(&spec, 1.0);
        assert_eq!(at.prescribed[0].u, [0.0, 0.0, 1.0]);
        assert_eq!(at.loads[0], static_load);
        assert_eq!(at.loads[1].force, [4.0, 0.0, 0.0]);
        let at = sim.spec_at(&spec, 0.5);
        assert_eq!(at.prescribed[0].u, [0.0, 0.0, 0.5]);
        assert_eq!(at.loads[0], static_load);
        assert_eq!(at.loads[1].force, [2.0, 0.0, 0.0]);
        assert_eq!(sim.spec_at(&spec, sim.end_time()), spec);
    }
}
