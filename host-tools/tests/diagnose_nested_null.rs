//! A candidate nested in the model's refined structure starts from that structure's fit
//! (`refit::fit_spec_on`), which diagnose makes once per step as the candidates' shared null
//! instead of once per nested candidate: the same fit, so the same model to the bit. Run in
//! release mode.

use lpvid_host::cli::run;
use lpvid_host::data::Dataset;
use lpvid_host::diagnose::effects::refined_null;
use lpvid_host::diagnose::plants::family_case;
use lpvid_host::diagnose::refit::{fit_spec, fit_spec_on, Spec};
use lpvid_host::model::{Factor, ModelFile};

/// The model `lpvid pbsid --train T <args>` writes for the records `train`.
fn pbsid_model(train: &Dataset, args: &[String]) -> ModelFile {
    let dir = tempfile::tempdir().unwrap();
    let tp = dir.path().join("train.csv");
    train.write_csv(&tp).unwrap();
    let mp = dir.path().join("m.json");
    let mut cli: Vec<String> = vec!["lpvid".into(), "pbsid".into(), "--train".into()];
    cli.push(tp.display().to_string());
    cli.extend(args.iter().cloned());
    cli.extend(["--out".to_string(), mp.display().to_string()]);
    run(cli, &mut Vec::new()).unwrap();
    ModelFile::read(&mp).unwrap()
}

/// Scheduling-nonlinearity plant 37000 of the family (order 4, p1^2 in A and B): the p1^2
/// basis and an added input channel u1^2, each nested in the user's structure refined, fitted
/// from that structure's own fit and from the fit given, are the same model file.
#[test]
fn a_nested_candidate_fitted_from_its_null_s_fit_is_the_same_fit() {
    let case = family_case("scheduling-nonlinearity", 37000, 1500).unwrap();
    let model = pbsid_model(&case.train, &["--past".into(), "7".into()]);
    let spec = Spec::from_model(&model, &mut vec![]).unwrap();
    let null = refined_null(&spec);
    let null_fit = fit_spec(&null, &case.train, &model.fit).unwrap();

    let mut p2 = spec.clone();
    p2.signals.scheduling.push(vec![Factor {
        pow: 2.0,
        ..Factor::col("p1")
    }]);
    let mut u2 = spec.clone();
    u2.signals.inputs.push(vec![Factor {
        pow: 2.0,
        ..Factor::col("u1")
    }]);
    // the structure fitted on the first half of the record: another start, which the nested
    // fit must be seen to use
    let half = Dataset {
        cols: case
            .train
            .cols
            .iter()
            .map(|c| c[..c.len() / 2].to_vec())
            .collect(),
        ..case.train.clone()
    };
    let other = fit_spec(&null, &half, &model.fit).unwrap();
    let mut moved = 0;
    for mut sp in [p2, u2] {
        sp.nested_in = Some(Box::new(null.clone()));
        let own = fit_spec(&sp, &case.train, &model.fit).unwrap();
        let given = fit_spec_on(&sp, &case.train, &model.fit, Some(&null_fit)).unwrap();
        assert_eq!(own.model, given.model);
        assert_eq!(own.order, given.order);
        let elsewhere = fit_spec_on(&sp, &case.train, &model.fit, Some(&other)).unwrap();
        moved += usize::from(elsewhere.model != own.model);
    }
    assert!(moved > 0, "the fit given is used");
}

/// A delayed input channel nested in a null that has fewer channels: the structure of a later
/// step carries a channel an earlier fix added beyond the null that fix was nested in. On
/// the EMPS benchmark (q_ref added at step 1, nested in the structure [u1] refined) every
/// step-2 variant delaying u1 failed with "a nested refinement adds input channels after
/// the null's or delays one of them". Here the family's input-delay plant 240105 (dead time
/// 5): u1(k-5) in place of u1 with u1^2 added after, nested in the user's structure [u1]
/// refined, fits, and its training free-run error is far below that null's (the dead time
/// is the plant's).
#[test]
fn a_delayed_channel_nests_in_a_null_with_fewer_channels() {
    let case = family_case("input-delay", 240105, 1500).unwrap();
    let model = pbsid_model(&case.train, &case.pbsid_args);
    let spec = Spec::from_model(&model, &mut vec![]).unwrap();
    assert_eq!(spec.signals.inputs.len(), 1);
    let null = refined_null(&spec);
    let null_fit = fit_spec(&null, &case.train, &model.fit).unwrap();
    let mut sp = spec.clone();
    sp.signals.inputs[0] = vec![Factor {
        delay: 5,
        ..Factor::col("u1")
    }];
    sp.signals.inputs.push(vec![Factor {
        pow: 2.0,
        ..Factor::col("u1")
    }]);
    sp.nested_in = Some(Box::new(null.clone()));
    let fitted = fit_spec_on(&sp, &case.train, &model.fit, Some(&null_fit)).unwrap();
    assert_eq!(fitted.model.signals.inputs.len(), 2);
    assert!(fitted.model.fit.get("nested_refinement").is_some());
    let vaf = |m: &ModelFile| {
        lpvid_host::simulate::score(m, &case.train, lpvid_host::simulate::Mode::FreeRun)
            .unwrap()
            .vaf_mean
    };
    let (v_null, v_delayed) = (vaf(&null_fit.model), vaf(&fitted.model));
    println!("training free-run VAF: null {v_null:.2} %, u1(k-5) with u1^2 {v_delayed:.2} %");
    assert!(
        v_delayed > v_null + 5.0 && v_delayed > 90.0,
        "{v_null} {v_delayed}"
    );
}
