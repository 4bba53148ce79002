#!/usr/bin/env bash
# Run 34's measures, as the rule reads them (docs/experiments/car_front/README.md), one after
# another: the judge (validation tracked and in the street world and mirrored, real dev, KITTI),
# the headings in the rows worlds with and without real greenhouses, the real dev cars one by
# one. Usage: eval_run34.sh RUN_DIR (holds model.safetensors); logs into RUN_DIR.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)
cd "$root"
run=${1:?usage: eval_run34.sh RUN_DIR}
py="$root/.venv/bin/python"
scripts/judge_candidate.sh "$run" 'tracking, street objects' 'tracking, mirrored' \
  > "$run/judge.log" 2>&1
for p in val-parked-roofs val-parked-rows; do
  "$py" docs/experiments/parked_rows/flips.py 8 40 suit_default "$run/candidate.safetensors" \
    "--preset=$p" > "$run/flips_$p.log" 2>&1
done
"$py" docs/experiments/either_way/real_headings.py ../shared/data/real-dev/av2 suit_default \
  "$run/candidate.safetensors" > "$run/real_headings.log" 2>&1
echo done > "$run/eval.done"
