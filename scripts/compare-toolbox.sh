#!/usr/bin/env bash
# Side by side: the PBSID toolbox (GNU Octave, its fit timed in-process with tic/toc) and
# lpvid (timed as a whole process: CSV read, fit, JSON write) on the same generated files,
# RUNS runs each (default 10), medians; prints the table of issue 16 (VAF on the fresh
# noise-free validation record, free run, mean over outputs).
#
#   scripts/compare-toolbox.sh [TOOLBOX_DIR]
#
# TOOLBOX_DIR: a checkout of github.com/TUDelft-DataDrivenControl/
# Predictor-Based-Subspace-IDentification-toolbox (default $PBSID_TOOLBOX). Without octave
# or the toolbox only the lpvid columns are filled. The toolbox is copied to a temporary
# directory and its private/reggcv.m patched for Octave (fminbnd with an anonymous function
# instead of extra arguments); the checkout itself is not changed.
set -euo pipefail
cd "$(dirname "$0")/.."
RUNS=${RUNS:-10}
TOOLBOX=${1:-${PBSID_TOOLBOX:-}}
WORK=$(mktemp -d)
trap 'rm -rf "$WORK"' EXIT

cargo build --release -q -p lpvid-host --bin lpvid --example gen_bench
LPVID=$PWD/target/release/lpvid
GEN=$PWD/target/release/examples/gen_bench
"$GEN" b1 1000 2016 "$WORK/b1.csv" "$WORK/b1v.csv"
"$GEN" b2 75 2016 "$WORK/b2.csv" "$WORK/b2v.csv"
"$GEN" b3 250 2016 "$WORK/b3.csv" "$WORK/b3v.csv"

# case: name | data | past | lpvid options | toolbox reg | toolbox opt | c | order
CASES=(
  "B1 p=3 Tikhonov-GCV|b1|3|--reg tikhonov-gcv|tikh|gcv|[0 0 0]|4"
  "B1 p=5 Tikhonov-GCV (kernel form)|b1|5|--reg tikhonov-gcv|tikh|gcv|[0 0 0]|4"
  "B2 p=5 Tikhonov-GCV|b2|5|--reg tikhonov-gcv|tikh|gcv|[0 1 0]|2"
  "B2 BPDN-SV p=5|b2|5|--reg bpdn-sv|bpdn|sv|[0 1 0]|2"
  "B2 BPDN-SV p=8|b2|8|--reg bpdn-sv|bpdn|sv|[0 1 0]|2"
  "B2 BPDN-SV p=10|b2|10|--reg bpdn-sv|bpdn|sv|[0 1 0]|2"
  "B3 BPDN-SV p=8|b3|8|--reg bpdn-sv|bpdn|sv|[0 0 0]|4"
  "B1 kernel p=8|b1|8|--kernel --reg tikhonov-gcv|tikh|gcv|[0 0 0]|4"
  "B1 kernel p=10|b1|10|--kernel --reg tikhonov-gcv|tikh|gcv|[0 0 0]|4"
)

HAVE_TB=0
if command -v octave >/dev/null && [ -n "$TOOLBOX" ] && [ -f "$TOOLBOX/lordvarx.m" ]; then
  HAVE_TB=1
  cp -r "$TOOLBOX" "$WORK/tb"
  python3 - "$WORK/tb/private/reggcv.m" <<'PY'
import re, sys
p = sys.argv[1]
s = open(p).read()
s2 = re.sub(r"fminbnd\(@reggcvfun,\.\.\.\s*\n(\s*)(reg_param\(min\(minGi\+1,npoints\)\)),\.\.\.\s*\n\s*(reg_param\(max\(minGi-1,1\)\)),OPT,Sn,beta\)",
            r"fminbnd(@(t) reggcvfun(t,Sn,beta),...\n\1\2,...\n\1\3,OPT)", s)
assert s2 != s, "reggcv.m: the fminbnd call was not found"
open(p, "w").write(s2)
PY
  cat > "$WORK/tbcase.m" <<'M'
function tbcase(train, val, p, reg, opt, c, n, runs)
  warning('off', 'all');
  d = dlmread(train, ',', 1, 0); v = dlmread(val, ',', 1, 0);
  h = strsplit(fgetl(fopen(train)), ',');
  r = sum(strncmp(h, 'u', 1)); l = sum(strncmp(h, 'y', 1)); s = sum(strncmp(h, 'p', 1));
  split = @(z) deal(z(:, 1:r), z(:, r+1:r+l), [ones(size(z, 1), 1) z(:, r+l+1:r+l+s)]);
  [u, y, mu] = split(d); [uv, yv, muv] = split(v);
  t = zeros(runs, 1);
  for k = 1:runs
    tic;
    [S, x] = lordvarx(u, y, mu, p, p, reg, opt, c);
    x = lmodx(x, n);
    [A, B, C, D] = lx2abcdk(x, u, y, mu, p, p, c);
    t(k) = toc;
  end
  m = s + 1; N = size(uv, 1); xs = zeros(n, 1); yid = zeros(N, l);
  Cm = reshape(C, l, n, []); Dm = reshape(D, l, r, []);
  for k = 1:N
    w = muv(k, :);
    yk = zeros(l, 1); xn = zeros(n, 1);
    for i = 1:size(Cm, 3), yk = yk + w(i) * (Cm(:, :, i) * xs + Dm(:, :, i) * uv(k, :)'); end
    for i = 1:m
      xn = xn + w(i) * (A(:, (i-1)*n+1:i*n) * xs + B(:, (i-1)*r+1:i*r) * uv(k, :)');
    end
    yid(k, :) = yk'; xs = xn;
  end
  vaf = 100 * max(0, 1 - var(yv - yid) ./ var(yv));
  if any(~isfinite(yid(:))), vaf(:) = 0; end
  printf('%.4f %.6f\n', mean(vaf), median(t));
end
M
fi

printf '| case | toolbox VAF / fit s | lpvid VAF / process s | ratio |\n|---|---|---|---|\n'
for c in "${CASES[@]}"; do
  IFS='|' read -r name data past opts treg topt cvec order <<<"$c"
  read -r lv lt < <(python3 - "$LPVID" "$WORK/$data.csv" "$WORK/${data}v.csv" "$past" "$WORK/m.json" "$RUNS" $opts <<'PY'
import json, statistics, subprocess, sys, time
exe, train, val, past, out, runs, *opts = sys.argv[1:]
times = []
for k in range(int(runs)):
    # a new model file in each run, as a user's first fit writes one: replacing an existing
    # file adds the fsync that guards it against power loss (0.4-10 ms on the project's VM),
    # which the toolbox, writing no file, does not pay
    cmd = [exe, "pbsid", "--train", train, "--val", val, "--past", past,
           "--out", f"{out}.{k}.json", "--json", *opts]
    t0 = time.perf_counter()
    res = subprocess.run(cmd, capture_output=True, text=True, check=True)
    times.append(time.perf_counter() - t0)
print(f"{json.loads(res.stdout)['val']['vaf_mean']:.2f} {statistics.median(times):.4f}")
PY
)
  if [ "$HAVE_TB" = 1 ]; then
    read -r tv tt < <(cd "$WORK/tb" && octave --no-gui --quiet --eval \
      "addpath('$WORK'); tbcase('$WORK/$data.csv', '$WORK/${data}v.csv', $past, '$treg', '$topt', $cvec, $order, $RUNS)" 2>/dev/null | tail -1)
    ratio=$(python3 -c "print(f'{$tt/$lt:.1f}')")
    printf '| %s | %.2f / %.4f | %s / %s | %s |\n' "$name" "$tv" "$tt" "$lv" "$lt" "$ratio"
  else
    printf '| %s | (no octave/toolbox) | %s / %s | |\n' "$name" "$lv" "$lt"
  fi
done
printf '\n%s, %s, %s cores, %s runs each, medians\n' "$(date -u +%F)" \
  "$(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)" "$(nproc)" "$RUNS"
