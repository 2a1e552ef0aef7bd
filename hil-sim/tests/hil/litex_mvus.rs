//! The hardware MVUs (gateware/) on the simulated LiteX SoC against the software MVU phase:
//! the same firmware solves on the SoC with four hardware MVUs under Verilator and on QEMU (the
//! portable kernel's numbers, as every software layout gives them), and every solution,
//! residual and iteration count must be bit-identical — on 1, 2 and 4 MVUs, with rows and
//! overlap partitions, the mirrored half of K and the whole of it, three directions fused and
//! one alone. Then `deform solve --target litex --mvus 4`'s own path refines to 1e-10.
//!
//! Needs `cargo xtask setup`, both firmwares (`cargo xtask firmware`, `cargo xtask firmware
//! --board litex`); set-up builds the 4-MVU SoC (a few minutes, cached; a run without it builds
//! it first).

use crate::support;

use std::time::{Duration, Instant};

use deform_hil_sim::litex::{litex_firmware_elf, LitexConfig, LitexSim, TEST_MVUS};
use deform_hil_sim::{firmware_elf, Qemu, QemuConfig};
use deform_host::board::BoardChoice;
use deform_host::encode::{encode_with, EncodeOptions, Partition};
use deform_host::link::{Target, Timeouts};
use deform_host::model::{Axis, Connection, Grid, Model, ModelSpec, Node, PointLoad};
use deform_host::solve::solve_model;
use deform_shared::protocol::{SolveParams, SolveReport, Start};

/// The hardware MVUs of the SoC these tests run on (`cargo xtask setup` builds it).
const MVUS: u8 = TEST_MVUS;

fn timeouts() -> Timeouts {
    Timeouts {
        handshake: Duration::from_secs(180),
        request: Duration::from_secs(120),
        solve: Duration::from_secs(900),
        ..Timeouts::default()
    }
}

/// A 4×4×4 cube of `connection`, corners fixed (A persymmetric), loads in all directions.
fn cube(connection: Connection) -> Model {
    Model::build(&ModelSpec {
        grid: Grid::new(4, 4, 4).unwrap(),
        connection,
        loads: vec![
            PointLoad {
                node: Node::new(0, 2, 1),
                force: [1.0, 0.5, -0.25],
            },
            PointLoad {
                node: Node::new(3, 1, 2),
                force: [0.0, -0.7, 2.0],
            },
        ],
        ..ModelSpec::thesis_example()
    })
    .expect("model builds")
}

/// Solves `rhs` (fused) for a fixed number of iterations; the report and the solutions.
fn solve(target: &mut Target, rhs: &[&[f64]], iterations: u32) -> (SolveReport, Vec<Vec<f64>>) {
    let params = SolveParams {
        max_iterations: iterations,
        tolerance: 1e-300,
        start: Start::Zero,
        directions: rhs.len() as u8,
        cycle_budget: 0,
    };
    target.solve_fused(rhs, params).expect("solve")
}

/// (model, MVUs, partition, mirrored half, three directions fused): every MVU count, both
/// partitions with both storage schemes on 4 MVUs for each model, and fused and single runs
/// each meeting both storage schemes. Eight cases, not the 24 of the full product: each case
/// costs seconds of Verilator time, and the gate has a time budget.
const CASES: &[(Connection, u8, Partition, bool, bool)] = &[
    (Connection::Axial, 1, Partition::Rows, true, true),
    (Connection::Axial, 2, Partition::Overlap, false, true),
    (Connection::Axial, 4, Partition::Rows, false, false),
    (Connection::Axial, 4, Partition::Overlap, true, false),
    (Connection::AxialShear, 1, Partition::Overlap, false, false),
    (Connection::AxialShear, 2, Partition::Rows, true, false),
    (Connection::AxialShear, 4, Partition::Overlap, true, true),
    (Connection::AxialShear, 4, Partition::Rows, false, true),
];

#[test]
fn hardware_mvus_give_the_software_kernels_results_bit_for_bit() {
    let sim = LitexSim::start(&LitexConfig::new(litex_firmware_elf()).with_mvus(MVUS))
        .unwrap_or_else(|e| panic!("cannot start the LiteX SoC with {MVUS} MVUs: {e}"));
    let mut litex = Target::connect(sim.serial_path().to_str().unwrap(), timeouts())
        .unwrap_or_else(|e| panic!("handshake: {e}; simulator:\n{}", sim.output()));
    assert_eq!(
        litex.info().harts,
        MVUS,
        "the firmware reports the hardware MVUs"
    );
    let qemu = Qemu::start(&QemuConfig::new(firmware_elf()).harts(8)).expect("QEMU");
    let mut virt = support::connect(&qemu);
    let started = Instant::now();
    for &(connection, mvus, partition, use_symmetry, fuse) in CASES {
        let model = cube(connection);
        let rhs: Vec<Vec<f64>> = Axis::ALL.iter().map(|&d| model.scaled_rhs(d)).collect();
        let fused: Vec<&[f64]> = rhs.iter().map(Vec::as_slice).collect();
        let options = EncodeOptions {
            mvus,
            partition,
            use_symmetry,
        };
        let encoding = encode_with(model.unit_matrix(), &options).unwrap();
        let label = format!("{connection:?} {options:?}");
        litex
            .upload_matrix(&encoding.matrix)
            .expect("upload (LiteX)");
        virt.upload_matrix(&encoding.matrix).expect("upload (QEMU)");
        let directions = if fuse { &fused[..] } else { &fused[..1] };
        let (hw, x_hw) = solve(&mut litex, directions, 8);
        let (sw, x_sw) = solve(&mut virt, directions, 8);
        assert_eq!(hw.mvus, mvus, "{label}");
        assert_eq!(hw.iterations, sw.iterations, "{label}");
        assert_eq!(hw.directions, sw.directions, "{label}: residuals");
        assert_eq!(hw.saturations, 0, "{label}");
        for (d, (a, b)) in x_hw.iter().zip(&x_sw).enumerate() {
            let same = a.iter().zip(b).all(|(p, q)| p.to_bits() == q.to_bits());
            assert!(same, "{label}: direction {d} differs");
        }
        println!(
            "{label}: {} direction(s), {} words, bit-identical; MVU phase {} cycles \
             ({} instructions) per iteration on the hardware MVUs",
            directions.len(),
            encoding.matrix.words.len(),
            hw.mvu.cycles / u64::from(hw.iterations.max(1)),
            hw.mvu.instructions / u64::from(hw.iterations.max(1)),
        );
    }
    println!("{:.1} s wall", started.elapsed().as_secs_f64());
}

#[test]
fn solve_on_four_hardware_mvus_refines_to_1e_10() {
    let model = cube(Connection::AxialShear);
    let mut plan = support::plan(
        BoardChoice::Litex {
            firmware: None,
            mvus: MVUS,
        },
        1e-10,
        8,
        Duration::from_secs(900),
    );
    plan.mvus = Some(MVUS);
    let solved = solve_model(&model, &plan).expect("solve on the LiteX SoC's hardware MVUs");
    let (rel, scale) = support::deviation_from_reference(&solved);
    assert!(scale > 0.0);
    assert!(rel <= 1e-8, "deviation {rel:e} of max |u|");
    let engine = solved.stats.engine.as_ref().expect("a target run");
    assert_eq!(engine.layout.mvus, MVUS);
    for d in &solved.stats.directions {
        assert!(d.relative_residual <= 1e-10, "{d:?}");
    }
}
