//! Benchmarks of `lpvid diagnose` (issue 7) on 10^4 and 10^5 samples, compared in the same
//! run with its peers: the plain validation of the model (free-run simulation + VAF/BFR, what
//! `lpvid validate` does) and one LPV-PBSID_opt refit of the model's structure (the unit of
//! work diagnose repeats for every candidate variant). Data: B2 (sparse paper Example I,
//! one input, one output, periodic scheduling) at 20 dB, validation of the same length;
//! model: `lpvid pbsid --past 3` (Tikhonov-GCV, order from the data). Figures in
//! docs/bench-diagnose.md.

use criterion::{black_box, criterion_group, criterion_main, BenchmarkId, Criterion};
use lpvid_host::cli::run;
use lpvid_host::data::Dataset;
use lpvid_host::diagnose::refit::{fit_spec, Spec};
use lpvid_host::diagnose::{diagnose, Options};
use lpvid_host::model::ModelFile;
use lpvid_host::pipeline::score;
use lpvid_host::simulate::Mode;
use lpvid_host::systems;

fn setup(n: usize, dir: &std::path::Path) -> (ModelFile, Dataset, Dataset) {
    let exp = systems::b2(n, 20.0, 1);
    let train = Dataset::from_signals(&exp.train, "train.csv");
    let val = Dataset::from_signals(&exp.val.slice(0, n), "val.csv");
    let tp = dir.join("train.csv");
    train.write_csv(&tp).unwrap();
    let mp = dir.join("m.json");
    let args = [
        "lpvid",
        "pbsid",
        "--train",
        tp.to_str().unwrap(),
        "--past",
        "3",
        "--out",
        mp.to_str().unwrap(),
    ];
    run(args, &mut Vec::new()).unwrap();
    (ModelFile::read(&mp).unwrap(), train, val)
}

fn bench(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let mut group = c.benchmark_group("diagnose");
    for n in [10_000usize, 100_000] {
        let (model, train, val) = setup(n, dir.path());
        group.sample_size(10);
        if n >= 100_000 {
            group.measurement_time(std::time::Duration::from_secs(60));
        }
        let id = format!("B2 N={n}");
        group.bench_function(
            BenchmarkId::new("validate (free run + VAF/BFR)", &id),
            |b| b.iter(|| black_box(score(&model, &val, Mode::FreeRun).unwrap())),
        );
        let spec = Spec::from_model(&model, &mut Vec::new()).unwrap();
        group.bench_function(BenchmarkId::new("one PBSID refit", &id), |b| {
            b.iter(|| black_box(fit_spec(&spec, &train, &model.fit).unwrap()))
        });
        group.bench_function(BenchmarkId::new("diagnose (no fix)", &id), |b| {
            b.iter(|| black_box(diagnose(&model, &train, &val, &Options::default()).unwrap()))
        });
        let fix = Options {
            fix: true,
            max_steps: 1,
            threads: 0,
        };
        group.bench_function(BenchmarkId::new("diagnose --fix", &id), |b| {
            b.iter(|| black_box(diagnose(&model, &train, &val, &fix).unwrap()))
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
