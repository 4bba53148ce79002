# Sourced by every project script: keep DDS on this machine, pick a per-run domain, use .venv.
# shellcheck shell=bash
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
# not ROS_LOCALHOST_ONLY: deprecated, and it overrides the discovery range
unset ROS_LOCALHOST_ONLY
if [ -z "${SUIT_ROS_KEEP_DOMAIN:-}" ]; then
  # a per-run domain id (1..100; ROS domains above 101 collide with ephemeral ports)
  ROS_DOMAIN_ID=$(( ( $$ + $(date +%s) ) % 100 + 1 ))
  export ROS_DOMAIN_ID
fi
export PYTHONUNBUFFERED=1
