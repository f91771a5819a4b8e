//! Fuzzing the data (CSV) and model (JSON) parsers with proptest: arbitrary bytes and mutated
//! valid files never panic, every error names its file, and what parses round-trips.
//!
//! The default is proptest's 256 cases per property (a few seconds in debug). For a long run:
//! `PROPTEST_CASES=200000 cargo test -p lpvid-host --release --test data_files`

use lpvid_host::data::{DataError, Dataset};
use lpvid_host::model::{ModelFile, SignalMap};
use proptest::prelude::*;

const CSV: &str = "t, u1,u2,y1,p1,q_ref\n\
0,1.5,-2e-3,0.25,0.1,7\n\
1,-0.5,1E+2,  0.5,0.2,7\n\
2,0,3,-1,0.3,\"8\"\n\
3,2.5,.5,4,0.4,9\r\n\
\n";

const SS: &str = r#"{
  "type": "lpv-ss",
  "inputs": [
    [{"col": "u1", "pow": 1, "delay": 0, "fn": null}],
    [{"col": "u2", "pow": 2, "delay": 1, "fn": "abs"}],
    [{"col": "k", "fn": "sin", "omega": 0.3}]
  ],
  "scheduling": [[], [{"col": "p1"}], [{"col": "p1", "pow": -1}, {"col": "q_ref", "fn": "sign"}]],
  "outputs": [[{"col": "y1"}]],
  "A": [[[0.5, 0.1], [0.0, 0.3]], [[0.1, 0.0], [0.2, 1e-3]], [[0.0, 0.0], [0.0, 0.1]]],
  "B": [[[1.0, 0.0, 0.5], [0.0, 1.0, 0.0]], [[0.5, 0.0, 0.0], [0.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]],
  "K": [[[0.2], [0.1]], [[0.0], [0.0]], [[0.0], [0.0]]],
  "C": [[[1.0, 0.0]], [[0.0, 0.1]], [[0.0, 0.0]]],
  "D": [[0.0, 0.0, 0.0]],
  "fit": {"method": "pbsid", "past": 5, "data": {"rows": 4, "note": "a \"quoted\" text"}}
}"#;

const ARX: &str = r#"{
  "type": "lpv-arx",
  "inputs": [[{"col": "u1"}], [{"col": "y1", "delay": 2, "fn": "cos", "omega": 1.5}]],
  "scheduling": [[], [{"col": "p1"}]],
  "outputs": [[{"col": "y1"}]],
  "na": 2, "nb": 1,
  "a": [[-0.5, 0.1], [0.2, 0.0]],
  "b": [[[1.0, 0.5], [0.0, 0.25]], [[0.1, 0.0], [0.0, 0.0]]],
  "fit": {}
}"#;

/// One edit of a text: insert, delete or replace at a position taken modulo its length.
#[derive(Debug, Clone)]
enum Edit {
    Insert(usize, String),
    Delete(usize, usize),
    Replace(usize, usize, String),
}

fn token() -> impl Strategy<Value = String> {
    prop_oneof![
        prop::sample::select(vec![
            ",",
            "\n",
            "\r\n",
            "\r",
            "\"",
            " ",
            "NaN",
            "nan",
            "inf",
            "-Infinity",
            "1e999",
            "1e-400",
            "[",
            "]",
            "{",
            "}",
            ":",
            "-",
            "0",
            "-1",
            "1e-3",
            "\u{feff}",
            "null",
            "true",
            "\"k\"",
            "\"col\"",
            "\"pow\"",
            "\"delay\"",
            "\"fn\"",
            "\"omega\"",
            "\"sin\"",
            "\"abs\"",
            "[]",
            "[[]]",
            "u1",
            "y1",
            "p1",
            "é",
            "18446744073709551616",
            "2147483648",
            "\\",
        ])
        .prop_map(str::to_owned),
        "[ -~]{0,6}",
    ]
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), token()).prop_map(|(i, t)| Edit::Insert(i, t)),
        (any::<usize>(), 1usize..8).prop_map(|(i, n)| Edit::Delete(i, n)),
        (any::<usize>(), 1usize..8, token()).prop_map(|(i, n, t)| Edit::Replace(i, n, t)),
    ]
}

/// Apply edits, keeping positions on character boundaries.
fn mutate(text: &str, edits: &[Edit]) -> String {
    let mut s = text.to_owned();
    let boundary = |s: &str, i: usize| {
        let mut i = if s.is_empty() { 0 } else { i % (s.len() + 1) };
        while !s.is_char_boundary(i) {
            i -= 1;
        }
        i
    };
    for e in edits {
        match e {
            Edit::Insert(i, t) => {
                let i = boundary(&s, *i);
                s.insert_str(i, t);
            }
            Edit::Delete(i, n) | Edit::Replace(i, n, _) => {
                let a = boundary(&s, *i);
                let b = boundary(&s, (a + n).min(s.len()));
                let with = if let Edit::Replace(_, _, t) = e {
                    t.as_str()
                } else {
                    ""
                };
                s.replace_range(a..b, with);
            }
        }
    }
    s
}

fn assert_named(e: &DataError, file: &str) {
    assert_eq!(e.file, file);
    assert!(!e.message.is_empty());
    assert!(e.to_string().starts_with(file), "{e}");
}

/// Parse CSV bytes; on success check the invariants and run the default signal map on it.
fn check_csv(bytes: &[u8]) -> Option<Dataset> {
    match Dataset::parse("fuzz.csv", bytes) {
        Ok(ds) => {
            assert!(!ds.is_empty());
            assert_eq!(ds.names.len(), ds.cols.len());
            for (i, (name, col)) in ds.names.iter().zip(&ds.cols).enumerate() {
                assert_eq!(col.len(), ds.len());
                assert!(col.iter().all(|v| v.is_finite()));
                assert!(!name.is_empty() && !ds.names[..i].contains(name));
            }
            match SignalMap::default_for(&ds).and_then(|m| m.evaluate(&ds)) {
                Ok(sig) => assert_eq!(sig.len(), ds.len()),
                Err(e) => assert_named(&e, "fuzz.csv"),
            }
            Some(ds)
        }
        Err(e) => {
            assert_named(&e, "fuzz.csv");
            None
        }
    }
}

/// Parse model JSON; on success it must round-trip and evaluate (or fail cleanly) on `ds`.
fn check_json(text: &str, ds: Option<&Dataset>) {
    match ModelFile::from_json_str("fuzz.json", text) {
        Ok(m) => {
            let again = ModelFile::from_json_str("again.json", &m.to_json_string())
                .unwrap_or_else(|e| panic!("written model does not read back: {e}"));
            assert_eq!(again, m);
            if let Some(ds) = ds {
                match m.signals.evaluate(ds) {
                    Ok(sig) => {
                        assert_eq!(sig.len(), ds.len());
                        assert_eq!(sig.p.ncols() + 1, m.signals.scheduling.len());
                    }
                    Err(e) => assert_named(&e, &ds.source),
                }
            }
        }
        Err(e) => {
            assert_named(&e, "fuzz.json");
            assert!(e.line.is_some(), "{e}");
        }
    }
}

#[test]
fn the_seeds_are_valid() {
    let ds = check_csv(CSV.as_bytes()).expect("seed CSV parses");
    assert_eq!(ds.len(), 4);
    for text in [SS, ARX] {
        let m = ModelFile::from_json_str("seed.json", text).unwrap();
        let sig = m.signals.evaluate(&ds).unwrap();
        assert_eq!(sig.len(), 4);
    }
}

proptest! {
    #[test]
    fn csv_arbitrary_bytes(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
        check_csv(&bytes);
    }

    #[test]
    fn csv_arbitrary_text(text in "[u1y1p,\n\r \"0-9.eE+\\-naif]{0,200}") {
        check_csv(text.as_bytes());
    }

    #[test]
    fn csv_mutated(edits in prop::collection::vec(edit(), 1..6)) {
        check_csv(mutate(CSV, &edits).as_bytes());
    }

    #[test]
    fn json_arbitrary_bytes(bytes in prop::collection::vec(any::<u8>(), 0..300)) {
        check_json(&String::from_utf8_lossy(&bytes), None);
    }

    #[test]
    fn json_mutated(edits in prop::collection::vec(edit(), 1..6), arx in any::<bool>()) {
        let ds = Dataset::parse("seed.csv", CSV.as_bytes()).unwrap();
        check_json(&mutate(if arx { ARX } else { SS }, &edits), Some(&ds));
    }

    #[test]
    fn mutated_model_on_mutated_data(
        model_edits in prop::collection::vec(edit(), 0..3),
        data_edits in prop::collection::vec(edit(), 0..3),
        arx in any::<bool>(),
    ) {
        let ds = check_csv(mutate(CSV, &data_edits).as_bytes());
        check_json(&mutate(if arx { ARX } else { SS }, &model_edits), ds.as_ref());
    }
}
