#!/usr/bin/env bash
# Measure a trained SUIT run against the shipped suit_default, as a ship rule reads it:
#   scripts/judge_candidate.sh RUN_DIR [VARIANT ...]
# RUN_DIR holds model.safetensors (suit-ros train --out). Writes into RUN_DIR:
#   candidate.safetensors  the model as it would ship (ship_suit in scripts/train_default.sh:
#                          input leveled to the local ground, memory sampling alpha 0.2,
#                          published thresholds chosen on the tune split, or with
#                          KEEP_THRESHOLDS=1 the shipped suit_default's) and thresholds.txt;
#   real_dev/              suit-ros report on ../shared/data/real-dev/av2 at node defaults, with
#                          --baseline suit_default (paired AP differences over places);
#   kitti/                 the same on ../shared/data/real-sample/kitti;
#   validation/            suit-ros compare --run before suit_default --run after candidate
#                          --variant tracking plus each VARIANT (default: 'tracking, street
#                          objects'), 16 validation drives, no held-out sensor.
# Write the rule before the run; this script only measures.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
. "$root/scripts/env.sh"
run=${1:?usage: scripts/judge_candidate.sh RUN_DIR [VARIANT ...]}
shift
[ -f "$run/model.safetensors" ] || { echo "no $run/model.safetensors: train first" >&2; exit 2; }
variants=("$@")
[ ${#variants[@]} -gt 0 ] || variants=('tracking, street objects')
suit="$root/.venv/bin/suit-ros"
py="$root/.venv/bin/python"
cand="$run/candidate.safetensors"
cp "$run/model.safetensors" "$cand"
"$py" scripts/ship_metadata.py "$cand" "candidate from $run"
if [ -n "${KEEP_THRESHOLDS:-}" ]; then       # the shipped suit_default's, not chosen again
  "$py" - "$cand" > "$run/thresholds.txt" <<'PY'
import sys
from suit_ros.checkpoint import default_checkpoint_path, read_metadata, update_metadata
meta = read_metadata(default_checkpoint_path())
update_metadata(sys.argv[1], publish_thresholds=meta['publish_thresholds'],
                publish_thresholds_source='kept from the shipped suit_default')
print('kept', meta['publish_thresholds'])
PY
else
  "$suit" choose-thresholds --checkpoint "$cand" --write > "$run/thresholds.txt"
fi
tail -6 "$run/thresholds.txt"
dev="$root/../shared/data"
if [ -d "$dev/real-dev/av2" ]; then
  "$suit" report --av2 "$dev/real-dev/av2" --checkpoint "$cand" --baseline suit_default \
    --out "$run/real_dev" > "$run/real_dev.log"
  sed -n '5,12p' "$run/real_dev/report.md"
  grep -A 8 '^## Against the baseline' "$run/real_dev/report.md"
fi
if [ -d "$dev/real-sample/kitti" ]; then
  "$suit" report --kitti "$dev/real-sample/kitti" --checkpoint "$cand" --baseline suit_default \
    --out "$run/kitti" > "$run/kitti.log"
fi
args=()
for v in "${variants[@]}"; do args+=(--variant "$v"); done
"$suit" compare --run before suit_default --run after "$cand" --variant tracking "${args[@]}" \
  --heldout-drives 0 --out "$run/validation" > "$run/compare.log"
grep -A 12 '^## Paired differences' "$run/validation/results.md"
