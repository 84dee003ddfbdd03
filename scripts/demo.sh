#!/usr/bin/env bash
# The main job: set up if needed, then run the simulated in-vitro session of the paper
# (section IV-B) end to end on the built-in defaults: default anatomy, the committed C-GAIL
# policy, 10 trials following the C-GAIL path and 10 following the centerline (3-minute
# limit each), every trial recorded to a bag, then the metrics table and box plots.
#   bash scripts/demo.sh                       # defaults, output in runs/invitro_session
#   bash scripts/demo.sh --trials 3 --mode dynamic --out runs/dyn   # any invitro_session option
set -euo pipefail
WS="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$WS"
bash scripts/setup.sh
# shellcheck disable=SC1091
source scripts/env.sh
# A domain of its own, so a demo never talks to a test run or another demo on this machine.
if [ "${ROS_DOMAIN_ID:-0}" = 0 ]; then export ROS_DOMAIN_ID=$(( (RANDOM % 42) + 60 )); fi
args=("$@")
if ! printf '%s\n' "${args[@]}" | grep -q -- '^--out'; then
    args+=(--out runs/invitro_session)
fi
echo "[demo] simulated in-vitro session (ROS_DOMAIN_ID=$ROS_DOMAIN_ID); Ctrl-C stops it cleanly"
exec "$WS/scripts/ros2run" cgail_planner invitro_session "${args[@]}"
