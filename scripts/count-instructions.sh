#!/usr/bin/env bash
# Cortex-M4F instruction counts of the core's per-sample and per-solve work (issue 18;
# the numbers in docs/bench-device.md):
#  1. counted run: the firmware's `count` image (firmware/src/bin/count.rs: the same core,
#     profile and float type as the device firmware) in QEMU mps2-an386 with
#     `-icount shift=0`, where every guest instruction advances the virtual clock by 1 ns and
#     SysTick counts that clock; a 2-instruction calibration loop gives instructions per tick.
#  2. static count: the Gram update's inner loops in the device firmware's own disassembly
#     (llvm-objdump or arm-none-eabi-objdump), instructions per packed entry.
# Instructions, not cycles (a Cortex-M4F load takes 2 cycles, vmla 3, vdiv/vsqrt 14).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD

command -v qemu-system-arm >/dev/null 2>&1 || bash scripts/setup.sh qemu-system-arm

echo "count: building the firmware images (thumbv7em-none-eabihf, release)"
(cd firmware && cargo build --release --quiet --target-dir "$ROOT/firmware/target")
BIN=$ROOT/firmware/target/thumbv7em-none-eabihf/release
echo "count: QEMU $(qemu-system-arm --version | head -1 | sed 's/.*version //'), -icount shift=0"
timeout 600 qemu-system-arm -machine mps2-an386 -cpu cortex-m4 -display none -icount shift=0 \
  -semihosting-config enable=on,target=native -serial stdio -kernel "$BIN/count" |
  sed 's/^/count: /'

OBJDUMP=""
for t in llvm-objdump arm-none-eabi-objdump; do
  command -v "$t" >/dev/null 2>&1 && { OBJDUMP=$t; break; }
done
if [ -z "$OBJDUMP" ]; then
  echo "count: no objdump found: static count skipped"
  exit 0
fi
echo "count: static, $OBJDUMP -d of the device firmware: loops of <= 24 instructions that load, multiply-add and store floats (the Gram update's row loops; one iteration per packed entry)"
"$OBJDUMP" -d --no-show-raw-insn "$BIN/lpvid-firmware" | python3 -c '
import re, sys
ins, func = [], ""
for l in sys.stdin:
    f = re.match(r"^[0-9a-f]+ <(.*)>:$", l)
    if f:
        func = f.group(1)
        continue
    m = re.match(r"\s+([0-9a-f]+):\s+(\S+)\s*(.*)", l)
    if m:
        ins.append((int(m.group(1), 16), m.group(2), m.group(3)))
idx = {a: k for k, (a, _, _) in enumerate(ins)}
for k, (a, mn, ops) in enumerate(ins):
    if not mn.startswith("b") or mn.startswith(("bl", "bx", "bkpt", "bic")):
        continue
    m = re.search(r"0x([0-9a-f]+)", ops)
    if not m or int(m.group(1), 16) >= a or int(m.group(1), 16) not in idx:
        continue
    body = ins[idx[int(m.group(1), 16)]:k + 1]
    mns = [b[1] for b in body]
    if len(body) > 24 or not any(x.startswith(("vstr", "vstm")) for x in mns) \
            or not any(x.startswith("vmla") for x in mns):
        continue
    kind = "compensated" if mns.count("vsub.f32") >= 2 else "plain"
    if "vmul.f32" in mns:
        kind += " with forgetting"
    print("count: loop 0x%x: %2d instructions per entry, %-28s %s" % (body[0][0], len(body), kind + ":", " ".join(mns)))
'
