# lpvid: the two commands of the README, and the steps they are made of.
# `make demo` runs the main job; `make test` runs every check CI runs.

# Debian packages the build and the tests need (installed by scripts/setup.sh if missing).
# libopenblas-dev: BLAS + LAPACK for clarabel's SDP cones (H-infinity observer LMI), opened at run time
# by host-tools/src/blas.rs (only a process that designs an observer loads it).
# qemu-system-arm: the firmware's Cortex-M4F board (mps2-an386) for make device-test.
DEB_PACKAGES := pkg-config libopenblas-dev qemu-system-arm

.PHONY: demo test test-long shared-data setup check-fmt clippy core-thumb host-lib test-all bench device-test device-count python-test

demo: setup
	cargo run --release -p lpvid-host --bin lpvid -- demo

test: setup check-fmt clippy core-thumb host-lib test-all device-test python-test

setup:
	bash scripts/setup.sh $(DEB_PACKAGES)

check-fmt:
	cargo fmt --all -- --check

clippy:
	cargo clippy --workspace --all-targets -- -D warnings

# The core must build for a Cortex-M4F with no allocator: the statistics alone
# (no default features: nalgebra + libm only, checked in the dependency tree) and with the
# wire protocol and device engine (feature `device`, what the firmware links).
core-thumb:
	cargo build -p lpvid --no-default-features --target thumbv7em-none-eabihf --release
	cargo build -p lpvid --no-default-features --features device --target thumbv7em-none-eabihf --release
	@tree=$$(cargo tree -p lpvid --no-default-features -e normal --prefix none); \
	if echo "$$tree" | grep -Eq '^(serde|postcard)'; then \
	  echo "core-thumb: the no-default-features core pulls wire crates:"; echo "$$tree"; exit 1; \
	fi; \
	echo "core-thumb: no-default-features dependencies: $$(echo "$$tree" | awk '{print $$1}' | sort -u | tr '\n' ' ')"

# The host library without the command line: clap and indicatif absent from its dependency
# list proves that no library module imports the CLI (layers: core <- library <- front ends).
host-lib:
	cargo check -p lpvid-host --lib --no-default-features
	@if cargo tree -p lpvid-host --no-default-features -e normal --prefix none | grep -Eq '^(clap|indicatif) '; then \
	  echo "host-lib: the library without the cli feature still pulls clap/indicatif"; exit 1; \
	fi; echo "host-lib: the library builds without the command line"

# Unit, integration and acceptance tests (release: the acceptance tests are Monte-Carlo runs).
# The measured-data tests (public benchmarks, cascaded tanks hold-out) read ../shared/data
# and skip without it: `make test` refuses to pass without them.
test-all: shared-data
	cargo test --workspace --release

# The long tier: the tests marked `#[ignore = "long tier: make test-long"]` (the measured
# benchmarks that take minutes each, more seeds and plants of the diagnosis' acceptance runs).
# Run it before merging a change to diagnose, refine or pbsid: CI runs `make test`, whose
# tier covers every behaviour once in about 10 minutes of tests on a 2-core machine of
# 2026-11 (about 25 minutes on those of 2026-12-07, three times slower).
test-long: setup shared-data
	cargo test --workspace --release -- --ignored

shared-data:
	@test -f ../shared/data/README.md || { echo "../shared/data is missing beside the checkout; the measured-data tests would be skipped"; exit 1; }

# The firmware in QEMU with its UART on a pseudo-terminal: stream a fixture through
# `lpvid device`, pull the statistics, compare with the file-based fit (scripts/device-test.sh).
device-test: setup
	bash scripts/device-test.sh

# Cortex-M4F instructions per sample and per solve: the firmware's count image in QEMU with
# -icount, and the Gram update's loops in the firmware's disassembly (docs/bench-device.md).
device-count: setup
	bash scripts/count-instructions.sh

# The Python package (host-tools/python): pip install of the path into target/pyenv, then
# its pytest suite (model round trip with the CLI, Dask equality on a 2-process cluster).
python-test:
	bash scripts/python-test.sh

bench:
	cargo bench --workspace
