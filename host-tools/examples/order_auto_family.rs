//! The order `--order auto` chooses, measured on random families of plants (issue 14, item
//! 5): for each plant of the diagnosis family (`plants::family_case_shaped`) the user's
//! `lpvid pbsid` is run with `--order auto`, and the order it keeps is set beside the plant's
//! true number of states, with the free-run error of both models on the plant's validation
//! record (from an estimated initial state, `pipeline::held_out_error`).
//! `cargo run --release -p lpvid-host --example order_auto_family -- [seeds] [N] [first seed]
//! [effects, comma-separated]` (defaults 20, 1500, 1000, `clean`); `LPVID_FAMILY_SHAPE=2x1`
//! etc. as in `diagnose_family`, and `LPVID_FAMILY_DUMP=DIR` writes each plant's records and
//! options as there. Prints one line per plant and the counts of orders below,
//! at and above the truth, and the spread of the validation error ratio (chosen / true
//! order). The figures are in docs/bench-diagnose.md.

use lpvid_host::diagnose::plants::{family_case_shaped, FamilyCase, Shape};
use lpvid_host::model::ModelFile;
use lpvid_host::pipeline::held_out_error;

/// The user's model with the order given as `order` ("auto" or a number), through the
/// command line as a user would fit it.
fn fit(case: &FamilyCase, order: &str) -> Result<ModelFile, String> {
    let dir = tempfile::tempdir().map_err(|e| e.to_string())?;
    let tp = dir.path().join("train.csv");
    let mp = dir.path().join("model.json");
    case.train.write_csv(&tp).map_err(|e| e.to_string())?;
    let mut args = case.pbsid_args.clone();
    match args.iter().position(|a| a == "--order") {
        Some(i) => args[i + 1] = order.to_string(),
        None => args.extend(["--order".to_string(), order.to_string()]),
    }
    let mut cli: Vec<String> = vec!["lpvid".into(), "pbsid".into(), "--train".into()];
    cli.push(tp.display().to_string());
    cli.extend(args);
    cli.extend(["--out".to_string(), mp.display().to_string()]);
    lpvid_host::cli::run(cli, &mut Vec::new()).map_err(|e| e.to_string())?;
    ModelFile::read(&mp).map_err(|e| e.to_string())
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let seeds: u64 = args.get(1).and_then(|s| s.parse().ok()).unwrap_or(20);
    let n: usize = args.get(2).and_then(|s| s.parse().ok()).unwrap_or(1500);
    let first: u64 = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(1000);
    let effects: Vec<String> = args.get(4).map_or(vec!["clean".to_string()], |l| {
        l.split(',').map(str::to_string).collect()
    });
    let shape = match std::env::var("LPVID_FAMILY_SHAPE") {
        Ok(text) => Shape::parse(&text).unwrap_or_else(|| {
            eprintln!("LPVID_FAMILY_SHAPE={text:?}: expected INPUTSxOUTPUTS, e.g. 2x2");
            std::process::exit(2)
        }),
        Err(_) => Shape::SISO,
    };
    let t0 = std::time::Instant::now();
    let (mut below, mut at, mut above) = (0, 0, 0);
    let mut ratios: Vec<f64> = Vec::new();
    for effect in &effects {
        for seed in first..first + seeds {
            let case = match family_case_shaped(effect, seed, n, shape) {
                Ok(c) => c,
                Err(e) => {
                    println!("{effect} seed {seed}: {e}");
                    continue;
                }
            };
            if let Ok(dir) = std::env::var("LPVID_FAMILY_DUMP") {
                if let Err(e) = case.dump(std::path::Path::new(&dir)) {
                    eprintln!("LPVID_FAMILY_DUMP: {e}");
                }
            }
            let truth = case.planted.states;
            let scored = fit(&case, "auto").and_then(|auto| {
                let fixed = fit(&case, &truth.to_string())?;
                let e = |m: &ModelFile| held_out_error(m, &case.val).map_err(|e| e.to_string());
                Ok((auto.clone(), e(&auto)?, e(&fixed)?))
            });
            let (auto, e_auto, e_true) = match scored {
                Ok(s) => s,
                Err(e) => {
                    println!("{effect} seed {seed}: {e}");
                    continue;
                }
            };
            let order = auto.fit["order"].as_u64().unwrap_or(0) as usize;
            match order.cmp(&truth) {
                std::cmp::Ordering::Less => below += 1,
                std::cmp::Ordering::Equal => at += 1,
                std::cmp::Ordering::Greater => above += 1,
            }
            let ratio = e_auto / e_true;
            ratios.push(ratio);
            let check = &auto.fit["order_check"];
            let gap = check["gap_order"]
                .as_u64()
                .map_or("-".into(), |g| g.to_string());
            println!(
                "{effect:<20} seed {seed:>6}: true {truth} gap {gap:>2} chosen {order:>2}  val VAF {:>7.3} / {:>7.3} % (chosen / true)  ratio {ratio:>6.2}  ({})",
                100.0 * (1.0 - e_auto),
                100.0 * (1.0 - e_true),
                case.description
            );
        }
    }
    ratios.sort_by(f64::total_cmp);
    let q = |f: f64| {
        ratios
            .get(((ratios.len().max(1) - 1) as f64 * f).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    println!(
        "\norder below the truth {below}, at {at}, above {above} ({} plants, N = {n}, {:.0} s); validation error ratio chosen / true order: median {:.2}, 90 % {:.2}, max {:.2}",
        below + at + above,
        t0.elapsed().as_secs_f64(),
        q(0.5),
        q(0.9),
        q(1.0)
    );
}
