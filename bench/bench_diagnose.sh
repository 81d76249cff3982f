#!/usr/bin/env bash
# CPU time of `trackcal-fit diagnose` on the paper preset against `trackcal-fit fit` of the same model
# (one fit of the base model, evaluated on the validation set) in the same run (docs/diagnose.md).
#
#   bench/bench_diagnose.sh [BUILD_DIR] [HIDDEN_EFFECT]      # e.g. build ferromagnetic_object
#
# The model is the paper room's planes and objects as fixed physical terms plus a degree-1
# polynomial: a model that fits the effect-free scene. Pin to one core: taskset -c 0 bench/...
set -euo pipefail
build=${1:-build}
hidden=${2:-ferromagnetic_object}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

"$build/sim/trackcal-simulate" --scene paper --hidden "$hidden" -o "$work/cap" > /dev/null
# Noise of the effect-free twin (per axis; orientation: the error quaternion's vector part).
"$build/sim/trackcal-simulate" --scene paper -o "$work/twin" > /dev/null
python3 - "$work" <<'EOF'
import json, math, sys
work = sys.argv[1]
floor = json.load(open(f"{work}/twin/truth.json"))["statistics"]["calib"]["noise_floor"]
sp = floor["position_mm"]["rms"] / math.sqrt(3)
so = 0.5 * floor["orientation_deg"]["rms"] / math.sqrt(3)
scene = json.load(open(f"{work}/twin/truth.json"))["effective"]["field_model"]
m = f"noise: {{position_mm: {sp}, orientation_deg: {so}}}\nterms:\n"
for p in scene["planes"]:
    m += (f"  - type: plane\n    name: {p['name']}\n    point_in_transmitter: {p['point_in_transmitter']}\n"
          f"    normal_in_transmitter: {p['normal_in_transmitter']}\n    attenuation: {p['attenuation']}\n"
          "    parameters: {distance_m: {fixed: true}, normal_in_transmitter: {fixed: true}, "
          "attenuation: {fixed: true}}\n")
for o in scene["objects"]:
    m += (f"  - type: dipole\n    name: {o['name']}\n    location_in_transmitter: {o['location_in_transmitter']}\n"
          f"    polarisability_m3: {o['polarisability_m3']}\n"
          "    parameters: {location_in_transmitter: {fixed: true}, polarisability_m3: {fixed: true}}\n")
m += "  - type: polynomial\n    degree: 1\n"
open(f"{work}/room.yaml", "w").write(m)
EOF

cpu() {  # user+sys CPU seconds of a command
  if ! /usr/bin/env time -f "%U %S" -o "$work/time" "$@" > /dev/null 2> "$work/err"; then
    cat "$work/err" >&2
    exit 1
  fi
  awk '{print $1+$2}' "$work/time"
}
fit_s=$(cpu "$build/fit/trackcal-fit" fit --data "$work/cap" --model "$work/room.yaml" -o "$work/c.json" --quiet)
diag_s=$(cpu "$build/fit/trackcal-fit" diagnose --data "$work/cap" --model "$work/room.yaml" --quiet)
python3 -c "f=$fit_s; d=$diag_s; print(f'fit: {f:.2f} s CPU; diagnose: {d:.2f} s CPU; ratio {d/f:.1f}')"
