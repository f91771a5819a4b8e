//! Issue 15 acceptance: for random argument combinations with an output aimed at an input
//! (by the same path, `./` spelling, a hard or symbolic link) or at a path that cannot be
//! written, the command fails before any work, with an error that says why, and no input
//! file changes (bytes and modification time).

use std::path::PathBuf;
use std::time::SystemTime;

use lpvid_host::cli::run;
use proptest::prelude::*;

const TRAIN: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/b1-train.csv");

/// The files of a case: training, validation and calibration data and a model.
struct Files {
    dir: tempfile::TempDir,
}

impl Files {
    fn new() -> Files {
        let dir = tempfile::tempdir().unwrap();
        for name in ["t.csv", "v.csv", "c.csv"] {
            std::fs::copy(TRAIN, dir.path().join(name)).unwrap();
        }
        std::fs::write(dir.path().join("m.json"), "{\"type\": \"lpv-ss\"}\n").unwrap();
        // a stand-in for the serial port (a regular file: opening it as a port fails)
        std::fs::write(dir.path().join("tty"), "").unwrap();
        std::fs::create_dir(dir.path().join("sub")).unwrap();
        Files { dir }
    }

    fn p(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }

    fn snapshot(&self) -> Vec<(PathBuf, Vec<u8>, SystemTime)> {
        ["t.csv", "v.csv", "c.csv", "m.json", "tty"]
            .iter()
            .map(|n| {
                let p = self.p(n);
                let m = std::fs::metadata(&p).unwrap().modified().unwrap();
                (p.clone(), std::fs::read(&p).unwrap(), m)
            })
            .collect()
    }
}

/// Where the output is aimed: one of the command's inputs (by index, spelled as given, with
/// `dir/sub/..`, through a hard link or a symbolic link), or a path that cannot be written.
#[derive(Debug, Clone, Copy)]
enum Target {
    Input(usize),
    Dotted(usize),
    HardLink(usize),
    SymLink(usize),
    UnderAFile,
    MissingDir,
    Directory,
}

impl Target {
    fn path(self, f: &Files, inputs: &[PathBuf]) -> PathBuf {
        let pick = |i: usize| inputs[i % inputs.len()].clone();
        match self {
            Target::Input(i) => pick(i),
            Target::Dotted(i) => {
                let p = pick(i);
                f.dir
                    .path()
                    .join("sub")
                    .join("..")
                    .join(p.file_name().unwrap())
            }
            Target::HardLink(i) => {
                let p = pick(i);
                let l = f.p("hard-link");
                std::fs::hard_link(&p, &l).unwrap();
                l
            }
            Target::SymLink(i) => {
                let l = f.p("sym-link");
                std::os::unix::fs::symlink(pick(i), &l).unwrap();
                l
            }
            Target::UnderAFile => f.p("t.csv").join("out.json"),
            Target::MissingDir => f.p("missing").join("out.json"),
            Target::Directory => f.p("sub"),
        }
    }

    fn aimed_at_input(self) -> bool {
        !matches!(
            self,
            Target::UnderAFile | Target::MissingDir | Target::Directory
        )
    }
}

fn target() -> impl Strategy<Value = Target> {
    prop_oneof![
        (0usize..4).prop_map(Target::Input),
        (0usize..4).prop_map(Target::Dotted),
        (0usize..4).prop_map(Target::HardLink),
        (0usize..4).prop_map(Target::SymLink),
        Just(Target::UnderAFile),
        Just(Target::MissingDir),
        Just(Target::Directory),
    ]
}

/// A command line without its output flag, the inputs it reads, and the output flag(s)
/// still to add (`OUT` marks the aimed one).
fn command(cmd: usize, which: usize, extra: &[bool], f: &Files) -> (Vec<String>, Vec<PathBuf>) {
    let s = |p: PathBuf| p.display().to_string();
    let mut a: Vec<String> = vec!["lpvid".into()];
    let mut inputs = Vec::new();
    let mut push = |v: &[&str]| a.extend(v.iter().map(|x| x.to_string()));
    match cmd {
        0 => {
            push(&["pbsid", "--train", &s(f.p("t.csv")), "--past", "2"]);
            inputs.push(f.p("t.csv"));
            if extra[0] {
                push(&["--val", &s(f.p("v.csv"))]);
                inputs.push(f.p("v.csv"));
            }
            if extra[1] {
                push(&["--json"]);
            }
            if extra[2] {
                push(&["--reg", "none", "--order", "2"]);
            }
            push(&["--out", "OUT"]);
        }
        1 => {
            push(&[
                "arx",
                "--train",
                &s(f.p("t.csv")),
                "--na",
                "1",
                "--nb",
                "1",
                "--ng",
                "1",
            ]);
            inputs.push(f.p("t.csv"));
            if extra[0] {
                push(&["--calib", &s(f.p("c.csv"))]);
                inputs.push(f.p("c.csv"));
            }
            if extra[1] {
                push(&["--val", &s(f.p("v.csv"))]);
                inputs.push(f.p("v.csv"));
            }
            push(&["--out", "OUT"]);
        }
        2 => {
            push(&[
                "simulate",
                "--model",
                &s(f.p("m.json")),
                "--data",
                &s(f.p("t.csv")),
            ]);
            inputs.extend([f.p("m.json"), f.p("t.csv")]);
            if extra[0] {
                push(&["--predictor"]);
            }
            push(&["--out", "OUT"]);
        }
        3 => {
            push(&[
                "diagnose",
                "--model",
                &s(f.p("m.json")),
                "--train",
                &s(f.p("t.csv")),
                "--val",
                &s(f.p("v.csv")),
            ]);
            inputs.extend([f.p("m.json"), f.p("t.csv"), f.p("v.csv")]);
            let other = s(f.p("report-other.json"));
            match (which, extra[0]) {
                (0, _) => push(&["--fix", "--out", "OUT"]),
                (_, false) => push(&["--json", "OUT"]),
                (_, true) => push(&["--fix", "--out", &other, "--json", "OUT"]),
            }
            if extra[1] {
                push(&["--plots", &s(f.p("plots"))]);
            }
        }
        _ => {
            push(&["device", "--port", &s(f.p("tty")), "pull"]);
            inputs.push(f.p("tty"));
            if extra[0] {
                push(&["--compare", &s(f.p("t.csv"))]);
                inputs.push(f.p("t.csv"));
            }
            if which == 0 {
                push(&["--out", "OUT"]);
            } else {
                push(&["--stats", "OUT"]);
            }
        }
    }
    (a, inputs)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 128, ..ProptestConfig::default() })]

    #[test]
    fn an_output_aimed_at_an_input_or_nowhere_changes_nothing(
        cmd in 0usize..5,
        which in 0usize..2,
        extra in prop::collection::vec(any::<bool>(), 3),
        t in target(),
    ) {
        let f = Files::new();
        let (mut args, inputs) = command(cmd, which, &extra, &f);
        let out = t.path(&f, &inputs).display().to_string();
        for a in args.iter_mut().filter(|a| *a == "OUT") {
            *a = out.clone();
        }
        let before = f.snapshot();
        let mut sink = Vec::new();
        let res = run(args.clone(), &mut sink);
        prop_assert!(before == f.snapshot(), "an input changed: {args:?}");
        let e = match res {
            Ok(()) => String::new(),
            Err(e) => e.to_string(),
        };
        prop_assert!(!e.is_empty(), "{args:?} succeeded");
        if t.aimed_at_input() {
            prop_assert!(e.contains("same file"), "{args:?}: {e}");
        } else {
            prop_assert!(
                e.contains("cannot write")
                    || e.contains("is a directory")
                    || e.contains("not a directory")
                    || e.contains("does not exist"),
                "{args:?}: {e}"
            );
        }
        // nothing left behind: no temporary file, no plots directory, no other output
        let stray: Vec<String> = std::fs::read_dir(f.dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".tmp") || n == "plots" || n == "report-other.json")
            .collect();
        prop_assert!(stray.is_empty(), "{args:?}: {stray:?}");
    }
}
