#!/usr/bin/env bash
# The recipe of the shipped checkpoint (suit_ros/checkpoints/suit_default.safetensors), on the
# 2-core CPU development machine: stage 1 single-frame pretraining (1200 steps, ~10 min), then
# every temporal variant fine-tuned 300 steps from it with the same budget (the ablation); the
# SUIT run is shipped. Seeds are in the configs. Writes runs/, docs/results.md.
set -euo pipefail
root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$root"
"$root/scripts/bootstrap"
. "$root/scripts/env.sh"
py="$root/.venv/bin/python"
"$root/.venv/bin/suit-ros" train --config params/train_single.yaml --out runs/stage1 --threads 2
"$py" scripts/ablation.py --stage1 runs/stage1/model.safetensors --steps 300 --ship
