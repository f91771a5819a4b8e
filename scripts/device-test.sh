#!/usr/bin/env bash
# make device-test: build the firmware, boot it in QEMU (mps2-an386, Cortex-M4F) with its
# UART on a pseudo-terminal, stream a fixture through `lpvid device`, pull the statistics
# and check them (and the model fitted from them) against the host's file-based result.
# The last line is a one-line summary.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

command -v qemu-system-arm >/dev/null 2>&1 || bash scripts/setup.sh qemu-system-arm

FIXTURE=${FIXTURE:-fixtures/b2-train.csv}
PAST=${PAST:-3}
# a longer stream for the throughput figure (8000 samples, r = l = s = 1)
SPEED_FIXTURE=${SPEED_FIXTURE:-fixtures/b6-train.csv}

echo "device-test: building the firmware (thumbv7em-none-eabihf, its own target dir)"
(cd firmware && cargo build --release --quiet --target-dir "$ROOT/firmware/target")
ELF=$ROOT/firmware/target/thumbv7em-none-eabihf/release/lpvid-firmware
echo "device-test: building the host tool"
cargo build --release --quiet -p lpvid-host --bin lpvid
LPVID=${CARGO_TARGET_DIR:-$ROOT/target}/release/lpvid

if command -v arm-none-eabi-size >/dev/null 2>&1; then
  arm-none-eabi-size "$ELF" | sed 's/^/device-test: /'
else
  llvm-size "$ELF" 2>/dev/null | sed 's/^/device-test: /' || true
fi

TMP=$(mktemp -d)
QPID=""
cleanup() {
  exec 3>&- 2>/dev/null || true
  exec 4>&- 2>/dev/null || true
  if [ -n "$QPID" ]; then kill "$QPID" 2>/dev/null || true; wait "$QPID" 2>/dev/null || true; fi
  rm -rf "$TMP"
}
trap cleanup EXIT

# -S: the guest waits until `cont`, so nothing it sends is lost before the port is open.
MON_PORT=$((20000 + RANDOM % 20000))
qemu-system-arm -machine mps2-an386 -cpu cortex-m4 -display none \
  -semihosting-config enable=on,target=native \
  -serial pty -monitor "tcp:127.0.0.1:$MON_PORT,server=on,wait=off" \
  -S -kernel "$ELF" >"$TMP/qemu.out" 2>"$TMP/qemu.err" &
QPID=$!

PTY=""
for _ in $(seq 100); do
  PTY=$(grep -o '/dev/pts/[0-9]*' "$TMP/qemu.out" 2>/dev/null | head -1 || true)
  [ -n "$PTY" ] && break
  kill -0 "$QPID" 2>/dev/null || { cat "$TMP/qemu.err" >&2; echo "device-test: QEMU exited" >&2; exit 1; }
  sleep 0.1
done
[ -n "$PTY" ] || { echo "device-test: QEMU printed no pseudo-terminal" >&2; exit 1; }
echo "device-test: QEMU $(qemu-system-arm --version | head -1 | sed 's/.*version //'), UART0 on $PTY"

# Hold the pseudo-terminal open for the whole session (QEMU drops output and is slow to
# reconnect while nobody has it open); this descriptor never reads.
exec 3<>"$PTY"
for _ in $(seq 50); do
  if exec 4<>"/dev/tcp/127.0.0.1/$MON_PORT" 2>/dev/null; then break; fi
  sleep 0.1
done
echo cont >&4

dev() { "$LPVID" device --port "$PTY" --json "$@"; }
retries() { local n; n=$(sed -n 's/.*"retries": *\([0-9]*\).*/\1/p' "$1" | head -1); echo "${n:-0}"; }
field() { sed -n "s/.*\"$2\": \\([-0-9.eE+a-z][-0-9.eE+a-z]*\\).*/\\1/p" "$1" | head -1; }
# the last integer value of a key (JSON lines: the summary comes last)
lastnum() { grep -o "\"$2\": *[0-9][0-9]*" "$1" | tail -1 | sed 's/.*: *//'; }
same_zero() {
  awk -v v="$1" 'BEGIN { exit !(v != "" && v + 0 == 0) }'
}

dev info >"$TMP/info.json"
echo "device-test: $(tr -d '\n ' <"$TMP/info.json" | grep -o '"info":{[^}]*}')"

dev stream "$FIXTURE" --past "$PAST" >"$TMP/stream.json"
SAMPLES=$(field "$TMP/stream.json" samples)
echo "device-test: streamed $SAMPLES samples of $FIXTURE (p = $PAST)"

dev pull --compare "$FIXTURE" --stats-tol 1e-5 --model-tol 1e-4 --out "$TMP/model.json" --stats "$TMP/stats.json" >"$TMP/pull.json"
STATS_DIFF=$(field "$TMP/pull.json" stats_vs_f64)
SAME_DIFF=$(field "$TMP/pull.json" stats_vs_same_type)
MODEL_DIFF=$(field "$TMP/pull.json" model_vs_file_fit)
WINDOWS=$(field "$TMP/pull.json" windows)
echo "device-test: pulled $(field "$TMP/pull.json" values) statistic values ($WINDOWS windows): vs host f64 $STATS_DIFF (relative), vs host f32 $SAME_DIFF; model vs file fit $MODEL_DIFF"
same_zero "$SAME_DIFF" || { echo "device-test: the pulled statistics differ from the host's f32 accumulation by $SAME_DIFF" >&2; exit 1; }

# f32 on the device vs f64 on the host: free-run VAF on the noise-free validation file
VAL=${FIXTURE_VAL:-${FIXTURE%-train.csv}-val.csv}
if [ -f "$VAL" ]; then
  "$LPVID" pbsid --train "$FIXTURE" --past "$PAST" --primal --out "$TMP/file-model.json" --json >/dev/null
  VAF_DEV=$("$LPVID" validate --model "$TMP/model.json" --data "$VAL" --json | sed -n 's/.*"vaf_mean": \([-0-9.eE+]*\).*/\1/p' | head -1)
  VAF_FILE=$("$LPVID" validate --model "$TMP/file-model.json" --data "$VAL" --json | sed -n 's/.*"vaf_mean": \([-0-9.eE+]*\).*/\1/p' | head -1)
  echo "device-test: free-run VAF on $VAL: model from the device's f32 statistics $VAF_DEV %, file fit in f64 $VAF_FILE %"
fi

dev solve --lambda-ratio 0.01 >"$TMP/solve.json"
echo "device-test: on-device Lasso: $(tr -d '\n ' <"$TMP/solve.json" | grep -o '"summary":{[^}]*}')"

# the model back to the device: its predictor runs on a second pass over the same data
dev push "$TMP/model.json" >"$TMP/push.json"
dev reset >"$TMP/reset.json"
dev stream "$FIXTURE" --past "$PAST" --resume >"$TMP/stream2.json"
dev info >"$TMP/info2.json"
PRED=$(tr -d '\n ' <"$TMP/info2.json" | grep -o '"prediction":{[^}]*}' || true)
echo "device-test: on-device one-step predictor after the second pass: $PRED"
[ -n "$PRED" ] || { echo "device-test: no prediction record" >&2; exit 1; }

# throughput: a longer file
dev stream "$SPEED_FIXTURE" --past 2 >"$TMP/speed.json"
RATE=$(field "$TMP/speed.json" samples_per_second)
SPEED_N=$(field "$TMP/speed.json" samples)
echo "device-test: throughput $SPEED_FIXTURE: $SPEED_N samples at $(printf '%.0f' "$RATE") samples/s through the emulated UART"

# issue 18: a drifting plant (B1 with its input matrices scaled 0.8 -> 1.2 over the record,
# p = 1: extended statistic vector 104) with forgetting, then with a sliding window. Each
# time the device runs its recursive estimate (a warm-started least-squares solve every
# $DRIFT_EVERY samples), `watch --compare` replays it on the host in f32 with the core's code
# and fails unless every reported parameter vector and one-step error is equal bit for bit;
# then the pulled statistics must equal the host's f32 replay exactly (0 difference).
DRIFT=${DRIFT_FIXTURE:-fixtures/b1-drift.csv}
DRIFT_PAST=${DRIFT_PAST:-1}
DRIFT_LAMBDA=${DRIFT_LAMBDA:-0.995}
DRIFT_WINDOW=${DRIFT_WINDOW:-1000}
DRIFT_EVERY=${DRIFT_EVERY:-500}
DRIFT_FILES=""
for mode in forgetting window; do
  if [ "$mode" = forgetting ]; then ACC=(--forgetting "$DRIFT_LAMBDA"); else ACC=(--window "$DRIFT_WINDOW"); fi
  dev watch "$DRIFT" --past "$DRIFT_PAST" "${ACC[@]}" --every "$DRIFT_EVERY" --lambda-ratio 0 --compare >"$TMP/watch-$mode.json"
  # JSON lines (one per estimate, then the summary): the summary's values are the last
  REPORTS=$(lastnum "$TMP/watch-$mode.json" reports_compared)
  IDENT=$(lastnum "$TMP/watch-$mode.json" identical)
  DSOLVES=$(lastnum "$TMP/watch-$mode.json" solves)
  [ -n "$REPORTS" ] && [ "$REPORTS" -gt 0 ] && [ "$REPORTS" = "$IDENT" ] || {
    echo "device-test: $mode: $IDENT of $REPORTS estimates equal to the host's replay" >&2; exit 1; }
  dev pull --compare "$DRIFT" --stats-tol 1e-4 >"$TMP/pull-$mode.json"
  D64=$(field "$TMP/pull-$mode.json" stats_vs_f64)
  D32=$(field "$TMP/pull-$mode.json" stats_vs_same_type)
  DWIN=$(field "$TMP/pull-$mode.json" windows)
  same_zero "$D32" || { echo "device-test: $mode: pulled statistics differ from the host's f32 replay by $D32" >&2; exit 1; }
  echo "device-test: drifting $DRIFT ($mode ${ACC[*]}, p = $DRIFT_PAST): $DSOLVES on-device solves, $IDENT of $REPORTS reported estimates equal to the host's f32 replay bit for bit; pulled statistics ($DWIN windows) vs host f32 $D32, vs host f64 $D64"
  DRIFT_FILES="$DRIFT_FILES watch-$mode pull-$mode"
done
DRIFT_N=$(tail -n +2 "$DRIFT" | wc -l)

# stack high-water mark: the firmware paints free RAM at boot; dump the top 256 KiB of RAM
# (the stack grows down from 0x2040_0000) and find the first untouched paint word
echo "pmemsave 0x203C0000 0x40000 \"$TMP/ram.bin\"" >&4
for _ in $(seq 50); do
  [ "$(stat -c %s "$TMP/ram.bin" 2>/dev/null || echo 0)" = 262144 ] && break
  sleep 0.1
done
STACK=$(od -An -v -t x4 -w4 "$TMP/ram.bin" 2>/dev/null | awk '{w[NR]=$1} END {run=0; for (i=NR; i>0; i--) { if (w[i]=="a5a5a5a5") { run++; if (run==16) { print (NR-(i+15))*4; exit } } else run=0 } print "unknown"}')
echo "device-test: firmware stack high-water mark: $STACK bytes (after configure, stream, pull, solve, push, predict, track)"

TOTAL_RETRIES=0
for f in info stream pull solve push reset stream2 info2 speed $DRIFT_FILES; do
  TOTAL_RETRIES=$((TOTAL_RETRIES + $(retries "$TMP/$f.json")))
done
STREAMED=$((SAMPLES * 2 + SPEED_N + 2 * DRIFT_N))
echo "device-test: PASS: $STREAMED samples streamed, $TOTAL_RETRIES frames retried, max statistic difference $STATS_DIFF (relative to f64 host; model output difference $MODEL_DIFF); drifting plant with forgetting and a window: device = host f32 bit for bit"
