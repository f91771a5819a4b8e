//! The public benchmarks of ../shared/data on their standard splits (docs/benchmarks-measured.md):
//! identify as a user would (`lpvid pbsid`), diagnose with `--fix` holding out the tail of the
//! training data, and print the test RMSE (data units) before and after, from x0 = 0 and with
//! the initial state estimated from the first 50 test samples.
//!
//! `cargo run --release --example benchmarks_measured [-- NAME...]` (names: silverbox, tanks,
//! disk, emps, rotor).

use std::path::{Path, PathBuf};

use lpvid_host::data::Dataset;
use lpvid_host::diagnose::{diagnose, Options};
use lpvid_host::model::ModelFile;
use lpvid_host::simulate::{run, Mode, X0};

fn segment(ds: &Dataset, lo: usize, hi: usize, tag: &str) -> Dataset {
    let hi = hi.min(ds.len());
    Dataset {
        source: format!("{}[{lo}..{hi}]{tag}", ds.source),
        names: ds.names.clone(),
        cols: ds.cols.iter().map(|c| c[lo..hi].to_vec()).collect(),
    }
}

fn rmse(model: &ModelFile, ds: &Dataset, x0: X0) -> f64 {
    let r = run(model, ds, Mode::FreeRun, x0).unwrap();
    let mut s = 0.0;
    let mut n = 0usize;
    for k in r.skip..r.y.nrows() {
        for j in 0..r.y.ncols() {
            let e = r.y[(k, j)] - r.yhat[(k, j)];
            s += e * e;
            n += 1;
        }
    }
    (s / n.max(1) as f64).sqrt()
}

fn main() {
    let dir = PathBuf::from("../shared/data");
    let dir = if dir.exists() {
        dir
    } else {
        PathBuf::from("../../shared/data")
    };
    let want: Vec<String> = std::env::args().skip(1).collect();
    let tmp = tempfile::tempdir().unwrap();
    for (name, file, train, test, past, order) in [
        (
            "silverbox",
            "silverbox-snls80mv.csv",
            (40960, 70960),
            vec![(100, 40575), (100, 32000)],
            "10",
            "auto",
        ),
        (
            "tanks",
            "cascaded-tanks-estimation.csv",
            (0, 1024),
            vec![(0, 1024)],
            "10",
            "auto",
        ),
        (
            "disk",
            "unbalanced-disk.csv",
            (0, 10000),
            vec![(10000, 15000)],
            "10",
            "auto",
        ),
    ] {
        if !want.is_empty() && !want.iter().any(|w| w == name) {
            continue;
        }
        let t0 = std::time::Instant::now();
        let ds = Dataset::read_csv(&dir.join(file)).unwrap();
        let tr = segment(&ds, train.0, train.1, "");
        let cut = tr.len() - tr.len() / 5;
        let (fit_part, hold) = (
            segment(&tr, 0, cut, " fit"),
            segment(&tr, cut, tr.len(), " held out"),
        );
        let tests: Vec<Dataset> = if name == "tanks" {
            vec![Dataset::read_csv(&dir.join("cascaded-tanks-validation.csv")).unwrap()]
        } else {
            test.iter()
                .map(|&(a, b)| segment(&ds, a, b, " test"))
                .collect()
        };
        let tf = tmp.path().join(format!("{name}.csv"));
        std::fs::write(&tf, fit_part.to_csv_bytes(&tf).unwrap()).unwrap();
        let mf = tmp.path().join(format!("{name}.json"));
        let mut out = Vec::new();
        lpvid_host::cli::run(
            [
                "lpvid",
                "pbsid",
                "--train",
                tf.to_str().unwrap(),
                "--past",
                past,
                "--order",
                order,
                "--out",
                mf.to_str().unwrap(),
            ],
            &mut out,
        )
        .unwrap();
        let model = ModelFile::read(Path::new(&mf)).unwrap();
        let o = diagnose(
            &model,
            &fit_part,
            &hold,
            &Options {
                fix: true,
                max_steps: 3,
                threads: 0,
            },
        )
        .unwrap();
        println!("== {name} ({:.0} s)", t0.elapsed().as_secs_f64());
        for a in &o.report.applied {
            println!(
                "  applied {}: {} ({:.1} %)",
                a.effect,
                a.detail,
                100.0 * a.explained
            );
        }
        println!("  stopped: {}", o.report.stopped);
        for f in o.report.findings.iter().take(4) {
            println!(
                "  finding {} {} explained {:.3} sig {}",
                f.effect, f.detail, f.explained, f.significant
            );
        }
        for t in &tests {
            println!(
                "  {}: RMSE before {:.4e} / x0 est {:.4e}; after {:.4e} / x0 est {:.4e}",
                t.source,
                rmse(&model, t, X0::Zero),
                rmse(&model, t, X0::Estimate { samples: 50 }),
                rmse(&o.model, t, X0::Zero),
                rmse(&o.model, t, X0::Estimate { samples: 50 }),
            );
        }
    }
}
