#!/bin/bash
# The bench harness's step (settle_after/bench_settle.py: the single frame, SUIT and the
# dense memory frame by frame in turn) under libgomp spin counts, in turn, REPS times.
# Usage: spin_ab.sh REPS THREADS "SPINCOUNTS" (e.g. "default 30000 3000"; default: unset)
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/../../.." && pwd)
source "$root/.venv/bin/activate" && source "$root/scripts/env.sh"
for r in $(seq "$1"); do for s in $3; do
  echo -n "spin $s: "
  if [ "$s" = default ]; then unset GOMP_SPINCOUNT; else export GOMP_SPINCOUNT=$s; fi
  python "$root/docs/experiments/settle_after/bench_settle.py" "$2" 60 suit_carry suit_default \
    2>&1 | grep threads | tr '\n' ' '
  echo
done; done
