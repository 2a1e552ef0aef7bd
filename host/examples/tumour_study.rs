//! The load-case and noise study behind docs/RESULTS.md's tumour table: the spring-field
//! estimator on the tumour case (a 12³ block with a 5× stiffer inclusion) for growing numbers
//! of load cases and replicate sets, three noise levels and three regularisations, each row
//! printed as a Markdown table line. About 30 s in release:
//!
//! ```text
//! cargo run -p deform-host --release --example tumour_study
//! ```
//!
//! It is a study, not a test: what it prints is the evidence docs/RESULTS.md cites; the
//! pass/fail check of the same case is the unit test `tumour_map_places_the_inclusion`.

use deform_host::inverse::regularise::Regularisation;
use deform_host::inverse::tumour::{distance_to_truth, tumour_model, tumour_observations};
use deform_host::inverse::{spring_field, Network, SpdSolver};

fn main() {
    let model = tumour_model(Vec::new());
    let net = Network::of(&model);
    let mut host: SpdSolver<'_, Box<dyn serialport::SerialPort>> = SpdSolver::Host { tol: 1e-14 };
    println!("| cases | sets/case | variance | regularisation | centre | distance | nodes | k̃ range | rel. residual | CG iterations |");
    println!("| ---: | ---: | ---: | --- | --- | ---: | ---: | --- | ---: | ---: |");
    for (cases, sets, var) in [
        (1, 1, 0.0),
        (1, 20, 1e-8),
        (2, 20, 1e-8),
        (4, 20, 1e-8),
        (4, 20, 1e-7),
        (4, 20, 1e-6),
    ] {
        let mut obs = tumour_observations(sets, var, 100);
        obs.sets.truncate(cases * sets);
        for reg in [
            vec![],
            vec![Regularisation::Smooth(1e-4)],
            vec![Regularisation::Tikhonov(1e-4)],
        ] {
            let names: Vec<String> = reg.iter().map(|r| r.to_string()).collect();
            let line = match spring_field::estimate(&net, &obs, &reg, &mut host) {
                Ok(est) => {
                    let c = est.stiff_region.centre;
                    format!(
                        "({:.2}, {:.2}, {:.2}) | {:.2} | {} | {:.2} – {:.2} | {:.1e} | {}",
                        c[0],
                        c[1],
                        c[2],
                        distance_to_truth(c),
                        est.stiff_region.nodes,
                        est.min_k,
                        est.max_k,
                        est.relative_residual,
                        est.solves.iterations
                    )
                }
                Err(e) => format!("refused: {e}"),
            };
            println!(
                "| {cases} | {sets} | {var:e} | {} | {line} |",
                names.join(" ")
            );
        }
    }
}
