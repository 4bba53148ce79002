# Sourced by every project script: keep DDS on this machine and pick a per-run domain, from
# the one helper the tests and the demo use too (suit_ros/rosenv.py).
# SUIT_ROS_KEEP_DOMAIN=1 keeps a ROS_DOMAIN_ID already set.
# shellcheck shell=bash
_suit_root=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
_suit_py="$_suit_root/.venv/bin/python"
[ -x "$_suit_py" ] || _suit_py=python3
eval "$(PYTHONPATH="$_suit_root${PYTHONPATH:+:$PYTHONPATH}" "$_suit_py" -m suit_ros.rosenv \
  ${SUIT_ROS_KEEP_DOMAIN:+--keep-domain})"
unset _suit_root _suit_py
