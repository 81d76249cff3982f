#!/usr/bin/env bash
# Time of `trackcal-fit diagnose` with the fast cross-validation (the default: folds refitted from
# the full fit) against `--exact-cv` (every fold fitted from scratch) in the same run, on the
# workflow tests' capture (tests/data/workflow/paper_small.yaml, 240 calibration stations) with a
# hidden effect, for the workflow's first two steps: a degree-4 polynomial, then sensor_offset plus
# the polynomial (docs/diagnose.md, Speed). Prints wall and CPU seconds, the ratios, and whether the
# two modes agree (verdict, significant candidates in order, largest relative difference of the
# held-out means).
#
#   bench/bench_diagnose.sh [BUILD_DIR] [HIDDEN_EFFECT] [SEED] [THREADS]   # build sensor_offset 1 0
#
# THREADS is diagnose's --threads (0: all cores). Say the machine's load when you quote the figures.
set -euo pipefail
build=${1:-build}
hidden=${2:-sensor_offset}
seed=${3:-1}
threads=${4:-0}
here=$(cd "$(dirname "$0")/.." && pwd)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

"$build/sim/trackcal-simulate" --scene "$here/tests/data/workflow/paper_small.yaml" \
  --hidden "$hidden" --seed "$seed" -o "$work/cap" > /dev/null
printf 'terms:\n  - type: polynomial\n    degree: 4\n' > "$work/step1.yaml"
printf 'terms:\n  - type: sensor_offset\n  - type: polynomial\n    degree: 4\n' > "$work/step2.yaml"

run() {  # run NAME ARGS...: diagnose --json into $work/NAME.json, "wall cpu" into $work/NAME.time
  local name=$1
  shift
  if ! /usr/bin/env time -f "%e %U %S" -o "$work/$name.time" "$build/fit/trackcal-fit" diagnose \
      --data "$work/cap" --threads "$threads" --json --quiet "$@" > "$work/$name.json" \
      2> "$work/$name.err"; then
    cat "$work/$name.err" >&2
    exit 1
  fi
}

echo "load average before: $(cut -d' ' -f1-3 /proc/loadavg); threads: $threads; $(nproc) cores"
for step in step1 step2; do
  run "$step.fast" --model "$work/$step.yaml"
  run "$step.exact" --model "$work/$step.yaml" --exact-cv
  python3 - "$work" "$step" <<'EOF'
import json, sys
work, step = sys.argv[1], sys.argv[2]
def load(mode):
    wall, user, sys_ = map(float, open(f"{work}/{step}.{mode}.time").read().split())
    return json.load(open(f"{work}/{step}.{mode}.json")), wall, user + sys_
fast, fw, fc = load("fast")
exact, ew, ec = load("exact")
sig = lambda d: [c["effect"] for c in d["candidates"] if c["significant"]]
worst = 0.0
pairs = [(fast["base"], exact["base"])]
by_effect = {c["effect"]: c for c in fast["candidates"]}
pairs += [(by_effect[c["effect"]], c) for c in exact["candidates"] if c["cross_validated"]]
for f, e in pairs:
    for key in ("cv_position_mm_mean", "cv_orientation_deg_mean"):
        worst = max(worst, abs(f[key] - e[key]) / abs(e[key]))
same = fast["verdict"]["effect"] == exact["verdict"]["effect"] and sig(fast) == sig(exact)
print(f"{step}: fast {fw:.2f} s wall, {fc:.2f} s CPU; exact {ew:.2f} s wall, {ec:.2f} s CPU; "
      f"speed-up {ew / fw:.1f}x wall, {ec / fc:.1f}x CPU")
print(f"  verdict {fast['verdict']['effect']} (exact: {exact['verdict']['effect']}), "
      f"significant {sig(fast)} (exact: {sig(exact)}): {'same' if same else 'DIFFERENT'}; "
      f"held-out means differ by at most {100 * worst:.3f} %")
EOF
done
echo "load average after: $(cut -d' ' -f1-3 /proc/loadavg)"
