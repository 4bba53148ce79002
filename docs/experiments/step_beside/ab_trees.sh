#!/bin/bash
# Two source trees (git worktrees) in turn, REPS times: step_overhead/bench_step.py in each
# (SUIT's step over the single frame's, the bench harness's runners and interleaving).
# Usage: ab_trees.sh BASE_TREE WORK_TREE CHECKPOINT THREADS REPS   (from WORK_TREE, its .venv)
base=$1; work=$2
source "$work/.venv/bin/activate" && source "$work/scripts/env.sh"
for r in $(seq "$5"); do
  for tree in "$base" "$work"; do
    echo -n "$tree "
    PYTHONPATH=$tree python "$tree/docs/experiments/step_overhead/bench_step.py" "$3" "$4" 60 2>&1 \
      | grep SUIT
  done
done
