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

/// Scheduling-nonlinearity plant 37000 of the family (order 4, p1^2 in A and B): the p1^2
/// basis and an added input channel u1^2, each nested in the user's structure refined, fitted
/// from that structure's own fit and from the fit given, are the same model file.
#[test]
fn a_nested_candidate_fitted_from_its_null_s_fit_is_the_same_fit() {
    let case = family_case("scheduling-nonlinearity", 37000, 1500).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let tp = dir.path().join("train.csv");
    case.train.write_csv(&tp).unwrap();
    let mp = dir.path().join("m.json");
    let args = [
        "lpvid",
        "pbsid",
        "--train",
        tp.to_str().unwrap(),
        "--past",
        "7",
        "--out",
        mp.to_str().unwrap(),
    ];
    run(args, &mut Vec::new()).unwrap();
    let model = ModelFile::read(&mp).unwrap();
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
