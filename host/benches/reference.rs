//! Criterion micro-benchmarks of the host baseline: the f64 reference CG's building blocks on
//! the thesis cube at growing sizes. Time per element should stay flat as n grows (everything
//! is linear in nnz). Run with `cargo bench -p deform-host --bench reference`; the sweep up to
//! 64³ nodes is `deform bench --host-baseline`.

use std::hint::black_box;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use deform_host::bench::BenchModel;
use deform_host::model::{Axis, Model};
use deform_host::reference;

const EDGES: [usize; 3] = [8, 16, 32];

fn cube(model: BenchModel, edge: usize) -> Model {
    Model::build(&model.cube(edge).expect("valid grid")).expect("valid model")
}

/// K·p, the MVU's job: one multiply-add per nonzero.
fn matrix_vector(c: &mut Criterion) {
    let mut group = c.benchmark_group("mul_vec");
    for model in BenchModel::BOTH {
        for edge in EDGES {
            let m = cube(model, edge);
            let a = m.unit_matrix();
            let x: Vec<f64> = (0..a.n()).map(|i| (i % 7) as f64).collect();
            let mut y = vec![0.0; a.n()];
            group.throughput(Throughput::Elements(a.nnz() as u64));
            group.bench_with_input(BenchmarkId::new(model.label(), a.n()), &a, |b, a| {
                b.iter(|| a.mul_vec_into(black_box(&x), &mut y))
            });
        }
    }
    group.finish();
}

/// Ten CG iterations from zero (tolerance 0, so exactly ten), set-up included.
fn cg_iterations(c: &mut Criterion) {
    let mut group = c.benchmark_group("cg_10_iterations");
    group.sample_size(20);
    for model in BenchModel::BOTH {
        for edge in EDGES {
            let m = cube(model, edge);
            let a = m.unit_matrix();
            let rhs = m.scaled_rhs(Axis::X);
            group.throughput(Throughput::Elements(10 * a.nnz() as u64));
            group.bench_with_input(BenchmarkId::new(model.label(), a.n()), &a, |b, a| {
                b.iter(|| reference::solve(a, black_box(&rhs), None, 0.0, 10).expect("SPD"))
            });
        }
    }
    group.finish();
}

/// Assembling the model: springs, fixed nodes, connectivity check, loads.
fn model_build(c: &mut Criterion) {
    let mut group = c.benchmark_group("model_build");
    group.sample_size(10);
    for model in BenchModel::BOTH {
        for edge in EDGES {
            let spec = model.cube(edge).expect("valid grid");
            let nnz = cube(model, edge).unit_matrix().nnz();
            group.throughput(Throughput::Elements(nnz as u64));
            group.bench_with_input(
                BenchmarkId::new(model.label(), edge * edge * edge),
                &spec,
                |b, spec| b.iter(|| Model::build(black_box(spec)).expect("valid model")),
            );
        }
    }
    group.finish();
}

criterion_group!(benches, matrix_vector, cg_iterations, model_build);
criterion_main!(benches);
