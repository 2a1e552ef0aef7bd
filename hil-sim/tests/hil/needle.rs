//! The dynamic needle of examples/needle-dynamic-8b.toml, loaded as the HIL tests and the
//! `dynamic_drift` example need it: one fixture, so that both measure the same session (the
//! example includes this file by path: deform-host is only a dev-dependency of hil-sim, so the
//! fixture cannot live in its library).
//!
//! The example file is part of the repository, so a failure to load it is a broken checkout,
//! and the loader panics with what failed.

/// examples/needle-dynamic-8b.toml as a dynamic live session (`deform live`) sees it: the
/// session set-up with the tool at rest, the dynamic model the scenario resolves to, and h.
pub struct DynamicNeedle {
    pub simulation: deform_host::scenario::Simulation,
    pub model: deform_host::model::ModelSpec,
    pub spec: deform_host::dynamics::DynamicsSpec,
    pub setup: deform_host::live::LiveSetup,
    pub h: f64,
}

impl DynamicNeedle {
    pub fn load(layout: &deform_host::encode::EncodeOptions) -> Self {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../examples/needle-dynamic-8b.toml"
        );
        let scenario = deform_host::scenario::Scenario::load(std::path::Path::new(path), None)
            .expect("the example loads");
        let simulation = scenario.simulation.clone().expect("a keyframed tool");
        let spec = deform_host::dynamics::flags::DynamicFlags::default()
            .resolve(simulation.dynamic, scenario.dynamics.as_ref())
            .unwrap()
            .expect("the example is dynamic");
        let setup =
            deform_host::live::LiveSetup::new(&simulation.spec_at(&scenario.model, 0.0), layout)
                .unwrap();
        Self {
            h: simulation.dt,
            simulation,
            model: scenario.model,
            spec,
            setup,
        }
    }

    /// The tool's displacement at frame `i` (t = i·h).
    pub fn tool(&self, i: u32) -> Vec<[f64; 3]> {
        let spec = self.simulation.spec_at(&self.model, f64::from(i) * self.h);
        vec![spec.prescribed[0].u]
    }

    /// Refined to `tol`, checked against the f64 stepper.
    pub fn params(
        &self,
        tol: f64,
        layout: deform_host::encode::EncodeOptions,
    ) -> deform_host::dynamics::target::DynamicParams {
        deform_host::dynamics::target::DynamicParams {
            tol,
            max_solves: 8,
            max_iterations: 500,
            check_reference: true,
            layout,
        }
    }
}
