#!/usr/bin/env bash
# The rule's measures (README.md), one after another, logs beside this script.
set -euo pipefail
here=$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)
cd "$here/../../.."
py=.venv/bin/python
$py "$here/measure.py" 16 40 --only=plain > "$here/val40_plain.log" 2>&1
$py "$here/measure.py" 16 40 --only=plain --preset=val-parked-rows > "$here/rows40_plain.log" 2>&1
$py "$here/measure.py" 16 100 > "$here/val100.log" 2>&1
$py "$here/measure.py" 16 40 --only=mirrored > "$here/val40_mirrored.log" 2>&1
