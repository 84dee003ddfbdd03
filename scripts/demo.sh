#!/usr/bin/env bash
# The main job: set up if needed, then run the simulated in-vitro session of the paper
# (section IV-B) end to end on the built-in defaults: default anatomy, the committed C-GAIL
# policy, the phantom's true catheter plant with the PAM model identified on it first
# (cgail identify-pam on the simulated bench), 30 trials following the C-GAIL path and 30 following
# the centerline (3-minute limit each), every trial recorded to a bag, then the metrics table
# and box plots.
#   bash scripts/demo.sh                       # defaults, output in runs/invitro_session
#   bash scripts/demo.sh --trials 3 --mode dynamic --out runs/dyn   # any cgail session option
set -euo pipefail
WS="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$WS"
bash scripts/setup.sh
# shellcheck disable=SC1091
source scripts/env.sh
# The session runs every trial on a free ROS domain of its own (or on ROS_DOMAIN_ID if you set
# it), and refuses a domain where a rig's device nodes answer.
args=("$@")
if ! printf '%s\n' "${args[@]}" | grep -q -- '^--out'; then
    args+=(--out runs/invitro_session)
fi
echo "[demo] simulated in-vitro session; Ctrl-C stops it and evaluates the trials done so far"
exec "$WS/scripts/ws" cgail session "${args[@]}"
