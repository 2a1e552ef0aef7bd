//! `deform bench --quick` on the firmware in QEMU: everything runs and what it writes is sane
//! (files parse, curves go the right way, plots are real pictures). Not a speed test: no figure
//! is compared with a threshold of time.

use std::path::{Path, PathBuf};

use deform_host::bench::convergence::Arithmetic;
use deform_host::bench::plan::{read_report, run, write_all, Choices};
use deform_host::bench::report::BenchReport;
use deform_host::bench::BenchModel;
use deform_host::board::TargetFlags;

fn out_dir() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("deform-bench-quick-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

fn strictly_increasing(values: &[f64]) -> bool {
    values.windows(2).all(|w| w[0] < w[1])
}

fn assert_picture(dir: &Path, stem: &str) {
    let svg = std::fs::read_to_string(dir.join(format!("{stem}.svg"))).unwrap();
    assert!(
        svg.starts_with("<svg") && svg.contains("<polyline") && svg.contains("<text"),
        "{stem}.svg has no lines or no text"
    );
    let png = std::fs::read(dir.join(format!("{stem}.png"))).unwrap();
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n", "{stem}.png");
    assert!(png.len() > 10_000, "{stem}.png is only {} bytes", png.len());
}

#[test]
fn quick_bench_runs_every_part_and_writes_sane_files() {
    let dir = out_dir();
    let quick = Choices {
        quick: true,
        ..Choices::default()
    };
    let (report, _) = run(&quick, &TargetFlags::default(), &dir).expect("deform bench --quick");

    // bench.json is the report, bench.csv the sweep.
    let json = std::fs::read_to_string(dir.join("bench.json")).unwrap();
    let parsed: BenchReport = serde_json::from_str(&json).unwrap();
    // (Floats may differ in their last digit after the decimal round trip.)
    let sweep_json = parsed.sweep.as_ref().unwrap();
    assert_eq!(
        sweep_json.points.len(),
        report.sweep.as_ref().unwrap().points.len()
    );
    assert_eq!(parsed.convergence.as_ref().map(Vec::len), Some(4));
    assert!(parsed.realtime.is_some() && parsed.host_baseline.is_some());
    assert!(parsed.quick && parsed.nominal_clock_hz == 100e6);
    let sweep = report.sweep.as_ref().unwrap();
    let csv = std::fs::read_to_string(dir.join("bench.csv")).unwrap();
    let rows: Vec<&str> = csv.lines().collect();
    assert_eq!(rows.len(), sweep.points.len() + 1);
    let columns = rows[0].split(',').count();
    assert!(rows.iter().all(|r| r.split(',').count() == columns));

    // The sweep: cost grows with n, model B costs more than A, figures are plausible.
    for model in BenchModel::BOTH {
        let points: Vec<_> = sweep
            .points
            .iter()
            .filter(|p| p.model == model && p.mvus == 1)
            .collect();
        assert!(points.len() >= 3, "{model}: {sweep:?}");
        let get = |f: fn(&&deform_host::bench::sweep::SweepPoint) -> f64| {
            points.iter().map(f).collect::<Vec<_>>()
        };
        assert!(strictly_increasing(&get(|p| p.n as f64)));
        assert!(
            strictly_increasing(&get(|p| p.cycles_per_iteration)),
            "{model}"
        );
        assert!(
            strictly_increasing(&get(|p| p.mvu_cycles_per_iteration)),
            "{model}"
        );
        assert!(
            strictly_increasing(&get(|p| p.wire_bytes_per_solve as f64)),
            "{model}"
        );
        for p in &points {
            assert!(p.mvu_cycles_per_iteration > 0.0 && p.svu_cycles_per_iteration > 0.0);
            assert!((1.0..200.0).contains(&p.instructions_per_nonzero), "{p:?}");
            assert!(p.mflops > 0.0 && p.mflops < 100.0, "{p:?}");
            // Conjugate symmetry stores about half of A (plus empty-row words of the tiling).
            assert!(
                p.words as usize >= p.nnz / 2 && p.words as usize <= p.nnz,
                "{p:?}"
            );
            assert_eq!(p.saturations, 0);
        }
    }
    // Two MVUs shorten the critical path of every point.
    for two in sweep.points.iter().filter(|p| p.mvus == 2) {
        let one = sweep
            .points
            .iter()
            .find(|p| p.model == two.model && p.n == two.n && p.mvus == 1)
            .unwrap();
        assert_eq!(two.mvus_used, 2);
        assert!(
            two.mvu_cycles_per_iteration < one.mvu_cycles_per_iteration,
            "{two:?}"
        );
        assert!(
            two.cycles_per_iteration < one.cycles_per_iteration,
            "{two:?}"
        );
    }
    assert!(sweep.points.iter().any(|p| p.mvus == 2));
    for a in sweep.points.iter().filter(|p| p.model == BenchModel::A) {
        let b = sweep
            .points
            .iter()
            .find(|p| p.model == BenchModel::B && p.n == a.n && p.mvus == a.mvus)
            .unwrap();
        assert!(b.mvu_cycles_per_iteration > a.mvu_cycles_per_iteration);
    }

    // Fig. 2-9: every curve ends far below where it starts; the target's refinement steps
    // each end lower than they began, and all reach the host's tolerance.
    let series = report.convergence.as_ref().unwrap();
    assert_eq!(series.len(), 4);
    for s in series {
        let first = s.points[0].1;
        assert!(s.final_error() < 1e-9 * first, "{s:?}");
        assert!(s.points.windows(2).all(|w| w[0].0 < w[1].0));
        if s.arithmetic == Arithmetic::FixedPoint {
            assert!(!s.refinement_starts.is_empty() && s.refinement_starts[0] == 0);
            assert!(s.final_relative_residual <= 1e-12, "{s:?}");
        }
    }
    let iterations = |m, a| {
        series
            .iter()
            .find(|s| s.model == m && s.arithmetic == a)
            .unwrap()
            .total_iterations()
    };
    assert!(
        iterations(BenchModel::B, Arithmetic::F64) < iterations(BenchModel::A, Arithmetic::F64)
    );

    // The real-time budget: every step costs cycles and bytes, verdicts follow the rate.
    for s in report.realtime.as_ref().unwrap() {
        assert_eq!(s.steps.len(), 3);
        assert!(s
            .steps
            .iter()
            .all(|st| st.cycles > 0 && st.iterations > 0 && st.wire_bytes > 0));
        assert_eq!(s.meets_haptic, s.compute_rate_hz >= 1000.0);
        assert_eq!(s.meets_visual, s.compute_rate_hz >= 60.0);
        assert!(s.wire_bytes_matrix_upload > 0);
    }

    // The host baseline grows with the problem.
    for model in BenchModel::BOTH {
        let host: Vec<_> = report
            .host_baseline
            .as_ref()
            .unwrap()
            .iter()
            .filter(|p| p.model == model)
            .collect();
        assert!(strictly_increasing(
            &host.iter().map(|p| p.nnz as f64).collect::<Vec<_>>()
        ));
        assert!(strictly_increasing(
            &host
                .iter()
                .map(|p| p.matrix_bytes as f64)
                .collect::<Vec<_>>()
        ));
        assert!(host.iter().all(|p| p.seconds_per_iteration > 0.0));
    }

    for stem in [
        "cycles_per_iteration",
        "mflops",
        "convergence",
        "realtime",
        "host_baseline",
    ] {
        assert_picture(&dir, stem);
    }
    // --replot redraws the pictures from bench.json alone.
    std::fs::remove_file(dir.join("mflops.svg")).unwrap();
    let replotted = read_report(&dir).expect("deform bench --replot");
    write_all(&replotted, &dir).expect("the plots redrawn");
    assert_eq!(
        replotted.sweep.map(|s| s.points.len()),
        Some(sweep.points.len())
    );
    assert_picture(&dir, "mflops");
    for csv in ["convergence.csv", "realtime.csv", "host_baseline.csv"] {
        assert!(
            std::fs::read_to_string(dir.join(csv))
                .unwrap()
                .lines()
                .count()
                > 2,
            "{csv}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
