#!/usr/bin/env bash
# Time of `trackcal-fit diagnose` against baselines in the same run, on the workflow tests' capture
# (tests/data/workflow/paper_small.yaml, 240 calibration stations) with a hidden effect, for the
# workflow's first two steps: a degree-4 polynomial, then the polynomial plus the first step's top
# candidate (sensor_offset, or for HIDDEN_EFFECT clock_offset the estimated time_offset, on the
# stream-only folder the loop uses: ~2400 stream samples). The baselines are
#   - one plain `trackcal-fit fit` of the same model on the same data (always: the diagnosis as a
#     multiple of one fit, which depends less on the machine's speed and load than seconds do), and
#   - by default `--exact-cv` of the same binary (every fold fitted from scratch), or
#   - with BASELINE_FIT=path/to/trackcal-fit, another build's binary with the same options (a
#     before/after comparison of a change: build the old commit elsewhere, or copy its binary).
# The runs alternate per step, so they see the same machine load. Prints wall and CPU seconds,
# the ratios, and whether the two diagnoses agree: verdict, significant candidates in order, the
# largest relative difference of the held-out means, and (before/after mode) of the reported
# parameters and their standard deviations.
#
#   bench/bench_diagnose.sh [BUILD_DIR] [HIDDEN_EFFECT] [SEED] [THREADS]   # build sensor_offset 1 0
#   BASELINE_FIT=/tmp/old/trackcal-fit bench/bench_diagnose.sh build clock_offset 1
#
# THREADS is diagnose's --threads (0: all cores); CROSS_VALIDATE_TOP its --cross-validate-top
# (default 3, the CLI's; the workflow loop uses 2). Say the machine's load when you quote figures.
set -euo pipefail
build=${1:-build}
hidden=${2:-sensor_offset}
seed=${3:-1}
threads=${4:-0}
baseline_fit=${BASELINE_FIT:-}
cv_top=${CROSS_VALIDATE_TOP:-3}
here=$(cd "$(dirname "$0")/.." && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

"$build/sim/trackcal-simulate" --scene "$here/tests/data/workflow/paper_small.yaml" \
  --hidden "$hidden" --seed "$seed" -o "$work/sim" > /dev/null
if [[ "$hidden" == clock_offset ]]; then  # the streams alone, as the workflow loop gives them
  mkdir "$work/cap"
  cp "$work/sim/tracker_stream.csv" "$work/sim/reference_stream.csv" "$work/cap/"
else
  ln -s "$work/sim" "$work/cap"
fi
printf 'terms:\n  - type: polynomial\n    degree: 4\n' > "$work/step1.yaml"
printf 'terms:\n  - type: sensor_offset\n  - type: polynomial\n    degree: 4\n' > "$work/step2.yaml"

# timed FILE COMMAND...: runs COMMAND, writes "wall user system" (seconds) into FILE and returns its
# status. Not GNU time: scripts/install-deps.sh does not install it (Debian's `time` package is
# optional, absent from a fresh bookworm), and python3 is there (the comparisons below use it).
timed() {
  local out=$1
  shift
  python3 -c '
import os, subprocess, sys, time
start = time.monotonic()
status = subprocess.run(sys.argv[2:]).returncode
wall = time.monotonic() - start
t = os.times()
with open(sys.argv[1], "w") as f:
    f.write(f"{wall:.3f} {t.children_user:.3f} {t.children_system:.3f}\n")
sys.exit(status if status >= 0 else 128 - status)
' "$out" "$@"
}
run() {  # run NAME BINARY ARGS...: diagnose --json into $work/NAME.json, "wall cpu" into NAME.time
  local name=$1 binary=$2
  shift 2
  if ! timed "$work/$name.time" "$binary" diagnose \
      --data "$work/cap" --threads "$threads" --cross-validate-top "$cv_top" --json --quiet "$@" \
      > "$work/$name.json" 2> "$work/$name.err"; then
    cat "$work/$name.err" >&2
    exit 1
  fi
}
fit_once() {  # fit_once NAME MODEL: one plain fit (the baseline), "wall cpu" into NAME.time
  local name=$1
  if ! timed "$work/$name.time" "$build/fit/trackcal-fit" fit \
      --data "$work/cap" --model "$2" -o "$work/$name.cal.json" --json --quiet \
      > "$work/$name.json" 2> "$work/$name.err"; then
    cat "$work/$name.err" >&2
    exit 1
  fi
}

if [[ -n "$baseline_fit" ]]; then
  mode="before/after"
  names=(after before)
else
  mode="fast/exact-cv"
  names=(fast exact)
fi
echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg); threads: $threads; $(nproc) cores;" \
  "comparing $mode"
for step in step1 step2; do
  if [[ "$step" == step2 && "$hidden" == clock_offset ]]; then
    # The loop's second model: the polynomial with the time offset the first diagnosis estimated.
    python3 - "$work/step1.${names[0]}.json" "$work/step2.yaml" <<'EOF'
import json, sys
doc = json.load(open(sys.argv[1]))
change = next(c["model_change"] for c in doc["candidates"] if c["effect"] == "time_offset")
open(sys.argv[2], "w").write(change + "terms:\n  - type: polynomial\n    degree: 4\n")
EOF
  fi
  fit_once "$step.fit" "$work/$step.yaml"
  if [[ -n "$baseline_fit" ]]; then
    run "$step.after" "$build/fit/trackcal-fit" --model "$work/$step.yaml"
    run "$step.before" "$baseline_fit" --model "$work/$step.yaml"
  else
    run "$step.fast" "$build/fit/trackcal-fit" --model "$work/$step.yaml"
    run "$step.exact" "$build/fit/trackcal-fit" --model "$work/$step.yaml" --exact-cv
  fi
  python3 - "$work" "$step" "${names[0]}" "${names[1]}" <<'EOF'
import json, math, sys
work, step, new_name, old_name = sys.argv[1:5]
def load(mode):
    wall, user, sys_ = map(float, open(f"{work}/{step}.{mode}.time").read().split())
    return json.load(open(f"{work}/{step}.{mode}.json")), wall, user + sys_
new, nw, nc = load(new_name)
old, ow, oc = load(old_name)
fw, fu, fs_ = map(float, open(f"{work}/{step}.fit.time").read().split())
# The fit's own figure (wall inside the process, single-threaded: reading, initialisation, solve,
# covariance): time's 10 ms resolution cannot time a lone polynomial's linear fit (~1 ms).
fc = max(json.load(open(f"{work}/{step}.fit.json"))["fit"]["seconds"], 1e-6)
sig = lambda d: [c["effect"] for c in d["candidates"] if c["significant"]]
def rel(a, b):
    if a is None or b is None:
        return 0.0 if a is None and b is None else math.inf
    return abs(a - b) / max(abs(b), 1e-300) if a != b else 0.0
worst = 0.0
pairs = [(new["base"], old["base"])]
# One row per (effect, term it replaces): a replacement shares its effect with the addition.
by_effect = {(c["effect"], c.get("replaces")): c for c in new["candidates"]}
pairs += [(by_effect[(c["effect"], c.get("replaces"))], c) for c in old["candidates"]
          if c["cross_validated"]]
for f, e in pairs:
    for key in ("cv_position_mm_mean", "cv_orientation_deg_mean"):
        worst = max(worst, rel(f[key], e[key]))
same = new["verdict"]["effect"] == old["verdict"]["effect"] and sig(new) == sig(old)
print(f"{step}: {new_name} {nw:.2f} s wall, {nc:.2f} s CPU; {old_name} {ow:.2f} s wall, "
      f"{oc:.2f} s CPU; speed-up {ow / nw:.2f}x wall, {oc / nc:.2f}x CPU")
print(f"  baseline, one plain fit of the model: {fc:.4f} s (the process: {fw:.2f} s wall); the "
      f"diagnosis's CPU takes {nc / fc:.0f} fits ({new_name}), {oc / fc:.0f} fits ({old_name})")
print(f"  verdict {new['verdict']['effect']} ({old_name}: {old['verdict']['effect']}), "
      f"significant {sig(new)} ({old_name}: {sig(old)}): {'same' if same else 'DIFFERENT'}; "
      f"held-out means differ by at most {100 * worst:.3g} %")
if old_name == "before":
    # Parameters and standard deviations of every fitted candidate, relative to the larger of the
    # value and its standard deviation (a parameter near zero is compared on its own scale).
    worst_value = worst_std = 0.0
    for c in old["candidates"]:
        n = by_effect.get((c["effect"], c.get("replaces")))
        if n is None or len(n["parameters"]) != len(c["parameters"]):
            worst_value = math.inf
            continue
        for pn, po in zip(n["parameters"], c["parameters"]):
            stds = [v for v in po["stddev"] if v is not None]
            block_scale = max(stds) if stds else 0.0
            for vn, vo in zip(pn["values"], po["values"]):
                worst_value = max(worst_value, abs(vn - vo) / max(abs(vo), block_scale, 1e-300))
            for sn, so in zip(pn["stddev"], po["stddev"]):
                worst_std = max(worst_std, rel(sn, so))
    print(f"  candidates' parameters differ by at most {worst_value:.2g} (relative), "
          f"standard deviations by at most {worst_std:.2g} (relative)")
EOF
done
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
