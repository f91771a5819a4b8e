//! The three exact forms of LPV-PBSID_opt agree: primal statistics with a data pass,
//! kernel (dual) form, and statistics alone (the device's path).

use lpvid::{PbsidDims, PbsidStats, StatsLayout};
use lpvid_host::lpvss::Signals;
use lpvid_host::pbsid::{fit, fit_from_stats, Order, PbsidOptions, Reg, Solver};
use lpvid_host::systems;

fn extended_stats(sig: &Signals, p: usize) -> PbsidStats<f64, Vec<f64>, Vec<f64>, Vec<f64>> {
    let dims = PbsidDims::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), p).unwrap();
    let len = lpvid::stat_vector_len(&dims, StatsLayout::Extended).unwrap();
    let mut st = PbsidStats::with_storage(
        dims,
        StatsLayout::Extended,
        vec![0.0; lpvid::window_storage_len(dims.r, dims.l, dims.s, p)],
        vec![0.0; lpvid::packed_len(len)],
        vec![0.0; len],
    )
    .unwrap();
    for k in 0..sig.len() {
        let u: Vec<f64> = sig.u.row(k).iter().copied().collect();
        let y: Vec<f64> = sig.y.row(k).iter().copied().collect();
        let pp: Vec<f64> = sig.p.row(k).iter().copied().collect();
        st.update(&u, &y, &pp).unwrap();
    }
    st
}

fn max_output_diff(
    a: &lpvid_host::lpvss::LpvSs,
    b: &lpvid_host::lpvss::LpvSs,
    sig: &Signals,
) -> f64 {
    let ya = a.simulate(sig, None);
    let yb = b.simulate(sig, None);
    (ya - &yb).amax() / sig.y.amax()
}

#[test]
fn stats_only_fit_equals_file_fit() {
    for (exp, p) in [(systems::b2(300, 25.0, 3), 3), (systems::b3(250, 4), 2)] {
        for reg in [Reg::None, Reg::TikhonovGcv] {
            let mut o = PbsidOptions::new(p);
            o.reg = reg;
            o.solver = Solver::Primal;
            let file = fit(&exp.train, &o).unwrap();
            let st = extended_stats(&exp.train, p);
            let dims = st.dims();
            let stats = fit_from_stats(st.gram(), &dims, &o).unwrap();
            assert_eq!(file.order, stats.order, "{}", exp.name);
            for (a, b) in file.singular_values.iter().zip(&stats.singular_values) {
                assert!((a - b).abs() <= 1e-8 * file.singular_values[0], "{a} {b}");
            }
            let diff = max_output_diff(&file.model, &stats.model, &exp.val);
            assert!(
                diff < 1e-7,
                "{} {reg:?}: relative output difference {diff}",
                exp.name
            );
        }
    }
}

#[test]
fn kernel_form_equals_primal_form() {
    let exp = systems::b3(250, 7);
    for reg in [Reg::None, Reg::TikhonovGcv] {
        let mut o = PbsidOptions::new(3);
        o.reg = reg;
        o.order = Order::Fixed(4);
        o.solver = Solver::Primal;
        let primal = fit(&exp.train, &o).unwrap();
        o.solver = Solver::Dual;
        let dual = fit(&exp.train, &o).unwrap();
        for (a, b) in primal.singular_values.iter().zip(&dual.singular_values) {
            assert!((a - b).abs() <= 1e-6 * primal.singular_values[0], "{a} {b}");
        }
        let diff = max_output_diff(&primal.model, &dual.model, &exp.val);
        assert!(diff < 1e-5, "{reg:?}: relative output difference {diff}");
    }
}

/// The streamed primal fit (`pbsid::stream`, two passes over chunks overlapping by p
/// samples) in `chunk`-sample pieces.
fn streamed(
    sig: &Signals,
    o: &lpvid_host::pbsid::PbsidOptions,
    chunk: usize,
) -> lpvid_host::pbsid::PbsidFit {
    use lpvid_host::pbsid::stream::PassOne;
    let mut one = PassOne::new(sig.u.ncols(), sig.y.ncols(), sig.p.ncols(), o).unwrap();
    let pieces: Vec<Signals> = (0..sig.len())
        .step_by(chunk)
        .map(|k| sig.slice(k, chunk.min(sig.len() - k)))
        .collect();
    for c in &pieces {
        one.update(c).unwrap();
    }
    assert_eq!(one.samples(), sig.len());
    let mut two = match one.finish(o) {
        Ok(t) => t,
        Err(e) => panic!("{e:?}"),
    };
    for c in &pieces {
        two.update(c).unwrap();
    }
    two.finish().unwrap()
}

#[test]
fn streamed_fit_equals_in_memory_fit_whatever_the_chunks() {
    for (exp, p) in [
        (systems::b1(1500, 0.05, 31), 2),
        (systems::b2(400, 25.0, 32), 4),
        (systems::b3(300, 33), 3),
    ] {
        for reg in [Reg::TikhonovGcv, Reg::None] {
            let mut o = PbsidOptions::new(p);
            o.reg = reg;
            o.solver = Solver::Primal;
            let mem = fit(&exp.train, &o).unwrap();
            // chunks shorter than p, odd sizes, one chunk
            for chunk in [1, p + 1, 97, exp.train.len()] {
                let st = streamed(&exp.train, &o, chunk);
                assert_eq!(mem.order, st.order, "{} chunk {chunk}", exp.name);
                assert_eq!(mem.windows, st.windows);
                for (a, b) in mem.singular_values.iter().zip(&st.singular_values) {
                    assert!((a - b).abs() <= 1e-7 * mem.singular_values[0], "{a} {b}");
                }
                assert_eq!(mem.scaling, st.scaling, "sums in the same order");
                let diff = max_output_diff(&mem.model, &st.model, &exp.val);
                assert!(
                    diff < 1e-7,
                    "{} {reg:?} chunk {chunk}: relative output difference {diff}",
                    exp.name
                );
            }
        }
    }
}

#[test]
fn streamed_file_fit_gives_the_in_memory_model() {
    use lpvid_host::model::ModelKind;
    use lpvid_host::pipeline::{identify, DataFile, PbsidSettings};
    use lpvid_host::stream::identify_streaming_chunks;
    let path = std::path::Path::new("../fixtures/b1-train.csv");
    let val = lpvid_host::data::Dataset::read_csv(std::path::Path::new("../fixtures/b1-val.csv"))
        .unwrap();
    for reg in [Reg::TikhonovGcv, Reg::None] {
        let mut settings = PbsidSettings::new(3);
        settings.fit.reg = reg;
        let mem = identify(&DataFile::read(path).unwrap(), Some(&val), &settings).unwrap();
        for chunk in [1, 5, 333, 4096] {
            let st = identify_streaming_chunks(path, Some(&val), &settings, chunk).unwrap();
            let (ModelKind::Ss(a), ModelKind::Ss(b)) = (&mem.model.kind, &st.model.kind) else {
                panic!()
            };
            let diff = max_output_diff(a, b, &systems::b1(1000, 0.0, 99).val);
            assert!(diff < 1e-7, "{reg:?} chunk {chunk}: {diff}");
            assert_eq!(mem.fit.order, st.fit.order);
            assert_eq!(mem.model.fit["train"], st.model.fit["train"], "file record");
            assert_eq!(mem.samples, st.samples);
            for (x, y) in mem.train_score.vaf.iter().zip(&st.train_score.vaf) {
                assert!((x - y).abs() < 1e-6, "{x} {y}");
            }
            let (vm, vs) = (
                mem.val_score.as_ref().unwrap(),
                st.val_score.as_ref().unwrap(),
            );
            assert!(
                (vm.vaf_mean - vs.vaf_mean).abs() < 1e-6,
                "{} {}",
                vm.vaf_mean,
                vs.vaf_mean
            );
            assert!((mem.observer.max_rho - st.observer.max_rho).abs() < 1e-6);
            assert_eq!(mem.observer.sbox.lo, st.observer.sbox.lo);
            assert_eq!(mem.observer.sbox.hi, st.observer.sbox.hi);
        }
    }
    // options that need the data are not streamed
    let mut settings = PbsidSettings::new(3);
    settings.fit.refine = true;
    assert!(identify_streaming_chunks(path, None, &settings, 100).is_none());
    // a bad file is left to the whole-file parser (its error names line and column)
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.csv");
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines: Vec<String> = text.lines().map(String::from).collect();
    lines[700] = lines[700].replacen(|c: char| c.is_ascii_digit(), "x", 1);
    std::fs::write(&bad, lines.join("\n")).unwrap();
    assert!(identify_streaming_chunks(&bad, None, &PbsidSettings::new(3), 100).is_none());
}
