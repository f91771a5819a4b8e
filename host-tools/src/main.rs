//! The `lpvid` command line; all logic lives in `lpvid_host::cli`.

fn main() {
    let mut stdout = std::io::stdout().lock();
    if let Err(e) = lpvid_host::cli::run(std::env::args_os(), &mut stdout) {
        eprintln!("{}", e.message());
        std::process::exit(2);
    }
}
