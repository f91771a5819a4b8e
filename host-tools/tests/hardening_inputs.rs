//! Issue 15, silent misreadings and hangs: every bad input gets an error (or a warning)
//! that says what is wrong, and nothing reads forever.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use lpvid_host::cli::run;

const LPVID: &str = env!("CARGO_BIN_EXE_lpvid");

fn lpvid(args: &[&str]) -> Result<String, String> {
    let mut out = Vec::new();
    let mut full = vec!["lpvid"];
    full.extend_from_slice(args);
    run(full, &mut out)
        .map(|_| String::from_utf8_lossy(&out).into_owned())
        .map_err(|e| e.message())
}

/// The binary's exit code, stdout and stderr.
fn binary(args: &[&str]) -> (i32, String, String) {
    let o = Command::new(LPVID).args(args).output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// `n` rows of a first-order LPV system, header `header` (three columns u, y, p).
fn rows(header: &str, n: usize) -> String {
    let mut t = format!("{header}\n");
    let mut y = 0.0;
    for k in 0..n {
        let f = k as f64;
        let u = (0.7 * f).sin() + 0.3 * (2.1 * f).cos();
        let p = 0.5 + 0.4 * (0.1 * f).sin();
        y = 0.5 * y + p * u;
        t.push_str(&format!("{u},{y},{p}\n"));
    }
    t
}

fn pbsid_err(dir: &Path, train: &Path) -> String {
    let out = dir.join("m.json");
    let e = lpvid(&[
        "pbsid",
        "--train",
        s(train),
        "--past",
        "2",
        "--out",
        s(&out),
    ])
    .unwrap_err();
    assert!(!out.exists(), "nothing may be written on error");
    e
}

#[test]
fn signal_numbering_gaps_are_errors_naming_the_column() {
    let dir = tempfile::tempdir().unwrap();
    let t = write(dir.path(), "t.csv", &rows("u2,y1,p1", 200));
    let e = pbsid_err(dir.path(), &t);
    assert!(
        e.contains("t.csv:1") && e.contains("'u2'") && e.contains("no u1"),
        "{e}"
    );
    let mut text = String::from("u1,u3,y1,y2,p1\n");
    for k in 0..50 {
        text.push_str(&format!("{k},{},{},{},0.5\n", k * 2, k % 3, k % 5));
    }
    let t = write(dir.path(), "g.csv", &text);
    let e = pbsid_err(dir.path(), &t);
    assert!(e.contains("'u3'") && e.contains("u2 is missing"), "{e}");
}

#[test]
fn a_blank_line_inside_the_data_is_an_error_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let mut lines: Vec<String> = rows("u1,y1,p1", 100).lines().map(String::from).collect();
    lines.insert(40, String::new());
    let t = write(dir.path(), "b.csv", &(lines.join("\n") + "\n\n\n"));
    let e = pbsid_err(dir.path(), &t);
    assert!(e.contains("b.csv:41") && e.contains("blank line"), "{e}");
    // trailing blank lines alone are fine
    let t = write(dir.path(), "ok.csv", &(rows("u1,y1,p1", 100) + "\n\n"));
    let out = dir.path().join("m.json");
    lpvid(&["pbsid", "--train", s(&t), "--past", "2", "--out", s(&out)]).unwrap();
}

#[test]
fn semicolons_and_decimal_commas_say_separator() {
    let dir = tempfile::tempdir().unwrap();
    let text = rows("u1,y1,p1", 50).replace(',', ";").replace('.', ",");
    let t = write(dir.path(), "semi.csv", &text);
    let e = pbsid_err(dir.path(), &t);
    assert!(e.contains("semi.csv:1") && e.contains("separator"), "{e}");
    let t = write(
        dir.path(),
        "comma.csv",
        "u1,y1,p1\n0,5,1,25,0,75\n1,5,2,0,0,5\n",
    );
    let e = pbsid_err(dir.path(), &t);
    assert!(e.contains("comma.csv:2") && e.contains("separator"), "{e}");
}

#[test]
fn overflowing_values_are_a_scale_problem_not_a_constant() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("u1,y1,p1\n");
    for line in rows("u1,y1,p1", 100).lines().skip(1) {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        text.push_str(&format!("{},{:e},{}\n", v[0], v[1] * 1e300, v[2]));
    }
    let t = write(dir.path(), "big.csv", &text);
    let e = pbsid_err(dir.path(), &t);
    assert!(
        e.contains("'y1'") && e.contains("too large") && e.contains("rescale"),
        "{e}"
    );
    assert!(!e.contains("constant"), "{e}");
    let mut text = String::from("u1,y1,p1\n");
    for line in rows("u1,y1,p1", 100).lines().skip(1) {
        let v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        text.push_str(&format!("{},{},{:e}\n", v[0], v[1], v[2] * 1e200));
    }
    let t = write(dir.path(), "bigp.csv", &text);
    let e = pbsid_err(dir.path(), &t);
    assert!(e.contains("'p1'") && e.contains("too large"), "{e}");
}

#[test]
fn a_degenerate_fit_warns_and_says_what_to_try() {
    let dir = tempfile::tempdir().unwrap();
    let t = write(dir.path(), "s75.csv", &rows("u1,y1,p1", 75));
    let out = dir.path().join("m.json");
    let (code, _, err) = binary(&["pbsid", "--train", s(&t), "--past", "40", "--out", s(&out)]);
    assert_eq!(code, 0, "{err}");
    assert!(
        err.contains("warning: degenerate fit") && err.contains("smaller --past"),
        "{err}"
    );
    let json = lpvid(&[
        "pbsid",
        "--train",
        s(&t),
        "--past",
        "40",
        "--out",
        s(&out),
        "--json",
    ])
    .unwrap();
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert!(
        v["warnings"].as_array().is_some_and(|w| !w.is_empty()),
        "{json}"
    );
    // a good fit has no warning
    let t = write(dir.path(), "good.csv", &rows("u1,y1,p1", 400));
    let (code, _, err) = binary(&["pbsid", "--train", s(&t), "--past", "2", "--out", s(&out)]);
    assert_eq!(code, 0);
    assert!(!err.contains("warning"), "{err}");
}

/// A plant that answers its input only after a dead time longer than the past window: the
/// fit is degenerate, the warning says to try a larger --past, and that one fits.
#[test]
fn a_dead_time_beyond_the_past_window_asks_for_a_larger_past() {
    let dir = tempfile::tempdir().unwrap();
    let mut text = String::from("u1,y1,p1\n");
    let (mut y, mut state) = (0.0, 7u64);
    let mut u = vec![0.0f64; 600];
    for k in 0..600 {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        u[k] = if (state >> 63) == 1 { 1.0 } else { -1.0 };
        let p = 0.5 + 0.4 * (0.05 * k as f64).sin();
        text.push_str(&format!("{},{y},{p}\n", u[k]));
        y = (0.5 + 0.3 * p) * y + if k >= 8 { u[k - 8] } else { 0.0 };
    }
    let t = write(dir.path(), "dead.csv", &text);
    let out = dir.path().join("m.json");
    let fit = |past: &str| {
        let (code, _, err) = binary(&[
            "pbsid",
            "--train",
            s(&t),
            "--past",
            past,
            "--order",
            "1",
            "--out",
            s(&out),
        ]);
        assert_eq!(code, 0, "{err}");
        err
    };
    let err = fit("3");
    assert!(
        err.contains("warning: degenerate fit") && err.contains("a larger --past (now 3, e.g. 6)"),
        "{err}"
    );
    let err = fit("12");
    assert!(!err.contains("degenerate"), "{err}");
}

#[test]
fn an_order_capped_by_max_order_warns() {
    let dir = tempfile::tempdir().unwrap();
    let t = concat!(env!("CARGO_MANIFEST_DIR"), "/../fixtures/b1-train.csv");
    let out = dir.path().join("m.json");
    let (code, _, err) = binary(&[
        "pbsid",
        "--train",
        t,
        "--past",
        "2",
        "--max-order",
        "1",
        "--out",
        s(&out),
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(err.contains("largest --max-order allows"), "{err}");
    // the default leaves room: no warning on the fixture
    let (_, _, err) = binary(&["pbsid", "--train", t, "--past", "2", "--out", s(&out)]);
    assert!(!err.contains("max-order"), "{err}");
}

#[test]
fn max_order_zero_and_negative_past_are_usage_errors() {
    let dir = tempfile::tempdir().unwrap();
    let t = write(dir.path(), "t.csv", &rows("u1,y1,p1", 100));
    let out = dir.path().join("m.json");
    let (code, _, err) = binary(&[
        "pbsid",
        "--train",
        s(&t),
        "--past",
        "2",
        "--max-order",
        "0",
        "--out",
        s(&out),
    ]);
    assert_eq!(code, 2);
    assert!(err.contains("--max-order") && err.contains("0"), "{err}");
    assert!(!out.exists());
    let (code, _, err) = binary(&["pbsid", "--train", s(&t), "--past", "-3", "--out", s(&out)]);
    assert_eq!(code, 2);
    assert!(!err.contains("error: error:"), "{err}");
}

/// A model that doubles its output every sample: y_k = x_k, x_{k+1} = 2 x_k + u_k.
const DIVERGING: &str = r#"{
  "type": "lpv-ss",
  "inputs": [[{"col": "u1"}]],
  "scheduling": [[]],
  "outputs": [[{"col": "y1"}]],
  "A": [[[2.0]]], "B": [[[1.0]]], "K": [[[0.0]]], "C": [[1.0]], "D": [[0.0]],
  "fit": {}
}"#;

/// Growing but finite: x_{k+1} = 1.5 x_k + u_k over 100 samples reaches about 1e18.
const GROWING: &str = r#"{
  "type": "lpv-ss",
  "inputs": [[{"col": "u1"}]],
  "scheduling": [[]],
  "outputs": [[{"col": "y1"}]],
  "A": [[[1.5]]], "B": [[[1.0]]], "K": [[[0.0]]], "C": [[1.0]], "D": [[0.0]],
  "fit": {}
}"#;

#[test]
fn validate_and_simulate_of_a_diverging_model_say_where() {
    let dir = tempfile::tempdir().unwrap();
    let m = write(dir.path(), "div.json", DIVERGING);
    let mut text = String::from("u1,y1\n");
    for k in 0..2000 {
        text.push_str(&format!("1,{}\n", k % 7));
    }
    let d = write(dir.path(), "d.csv", &text);
    let human = lpvid(&["validate", "--model", s(&m), "--data", s(&d)]).unwrap();
    assert!(human.contains("diverged at sample"), "{human}");
    let json = lpvid(&["validate", "--model", s(&m), "--data", s(&d), "--json"]).unwrap();
    let v: serde_json::Value = serde_json::from_str(&json).unwrap();
    let k = v["score"]["diverged_at"]
        .as_u64()
        .expect("diverged_at in the JSON");
    assert!(k > 300 && k < 400, "{k}");
    assert!(v["diverged"]
        .as_str()
        .unwrap()
        .contains("diverged at sample"));
    let out = dir.path().join("sim.csv");
    let e = lpvid(&[
        "simulate",
        "--model",
        s(&m),
        "--data",
        s(&d),
        "--out",
        s(&out),
    ])
    .unwrap_err();
    assert!(e.contains(&format!("diverged at sample {k}")), "{e}");
    assert!(!out.exists());
    // a large but finite run is written in exponent form, never as 96 digits
    let m = write(dir.path(), "grow.json", GROWING);
    let mut text = String::from("u1,y1\n");
    for _ in 0..100 {
        text.push_str("1,0\n");
    }
    let d = write(dir.path(), "g.csv", &text);
    lpvid(&[
        "simulate",
        "--model",
        s(&m),
        "--data",
        s(&d),
        "--out",
        s(&out),
    ])
    .unwrap();
    let written = std::fs::read_to_string(&out).unwrap();
    assert!(written.lines().all(|l| l.len() < 60), "{written}");
    assert!(written.contains("e17"), "{written}");
}

#[test]
fn inputs_that_never_end_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("m.json");
    let t0 = Instant::now();
    for dev in ["/dev/zero", "/dev/urandom"] {
        let e = lpvid(&["pbsid", "--train", dev, "--past", "2", "--out", s(&out)]).unwrap_err();
        assert!(e.contains(dev) && e.contains("not a regular file"), "{e}");
        let e = lpvid(&["validate", "--model", dev, "--data", dev]).unwrap_err();
        assert!(e.contains("not a regular file"), "{e}");
    }
    assert!(t0.elapsed() < Duration::from_secs(5));
    // a pipe is read, but a line longer than 1 MiB stops it
    let fifo = dir.path().join("in.fifo");
    if Command::new("mkfifo")
        .arg(&fifo)
        .status()
        .is_ok_and(|s| s.success())
    {
        let f2 = fifo.clone();
        let writer = std::thread::spawn(move || {
            use std::io::Write;
            let mut f = std::fs::OpenOptions::new().write(true).open(f2).unwrap();
            let chunk = vec![b'1'; 64 * 1024];
            for _ in 0..40 {
                if f.write_all(&chunk).is_err() {
                    break;
                }
            }
        });
        let e = lpvid(&[
            "pbsid",
            "--train",
            s(&fifo),
            "--past",
            "2",
            "--out",
            s(&out),
        ])
        .unwrap_err();
        assert!(e.contains(":1") && e.contains("line longer than"), "{e}");
        writer.join().unwrap();
    }
}

#[test]
fn device_commands_check_local_files_before_the_port() {
    let dir = tempfile::tempdir().unwrap();
    let bad = write(dir.path(), "bad.csv", "u1,y1\n1,x\n");
    // the port does not exist: the file's error comes first
    let e = lpvid(&["device", "--port", "/nonexistent/tty", "stream", s(&bad)]).unwrap_err();
    assert!(e.contains("bad.csv:2"), "{e}");
    let m = write(dir.path(), "m.json", "{\"type\": \"lpv-ss\"");
    let e = lpvid(&["device", "--port", "/nonexistent/tty", "push", s(&m)]).unwrap_err();
    assert!(e.contains("m.json"), "{e}");
    let e = lpvid(&["device", "--port", "/nonexistent/tty", "push", "/dev/zero"]).unwrap_err();
    assert!(e.contains("not a regular file"), "{e}");
}

#[test]
fn device_timeout_is_honoured_for_the_handshake_and_announced() {
    let Ok((_master, slave)) = serialport::TTYPort::pair() else {
        return; // no pseudo-terminals here
    };
    use serialport::SerialPort;
    let name = slave.name().expect("pty name");
    let t0 = Instant::now();
    let (code, _, err) = binary(&[
        "device",
        "--port",
        &name,
        "--timeout-ms",
        "200",
        "--retries",
        "2",
        "info",
    ]);
    let took = t0.elapsed();
    assert_eq!(code, 2, "{err}");
    // 3 attempts x 200 ms (the old first-reply wait was 3000 ms per attempt)
    assert!(took < Duration::from_millis(2500), "{took:?}");
    assert!(
        err.contains(&format!("waiting for the device on {name}")) && err.contains("200 ms x 3"),
        "{err}"
    );
    assert!(err.contains("no valid reply"), "{err}");
    // --quiet and --json say nothing but the error
    let (_, _, err) = binary(&[
        "device",
        "--port",
        &name,
        "--timeout-ms",
        "50",
        "--retries",
        "0",
        "--quiet",
        "info",
    ]);
    assert!(!err.contains("waiting"), "{err}");
}
