# lpvid: the two commands of the README, and the steps they are made of.
# `make demo` runs the main job; `make test` runs every check CI runs.

# Debian packages the build and the tests need (installed by scripts/setup.sh if missing).
# libopenblas-dev: BLAS + LAPACK for clarabel's SDP cones (H-infinity observer LMI), linked by host-tools/build.rs.
DEB_PACKAGES := pkg-config libopenblas-dev

.PHONY: demo test setup check-fmt clippy core-thumb test-all bench

demo: setup
	cargo run --release -p lpvid-host --bin lpvid -- demo

test: setup check-fmt clippy core-thumb test-all

setup:
	bash scripts/setup.sh $(DEB_PACKAGES)

check-fmt:
	cargo fmt --all -- --check

clippy:
	cargo clippy --workspace --all-targets -- -D warnings

# The core must build for a Cortex-M4F with no allocator.
core-thumb:
	cargo build -p lpvid --target thumbv7em-none-eabihf --release

# Unit, integration and acceptance tests (release: the acceptance tests are Monte-Carlo runs).
test-all:
	cargo test --workspace --release

bench:
	cargo bench --workspace
