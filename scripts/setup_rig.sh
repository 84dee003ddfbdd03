#!/usr/bin/env bash
# The lean rig install: only what the rig PC runs, into a fresh venv, without torch or the
# training stack. Installs requirements-rig.txt into PREFIX/venv and builds the device packages
# (em_tracker, pam_controller, catheter_driver) and the planner (cgail_planner) with what they
# depend on (cgail_sim, cgail_node_utils, tf2_msgs) into PREFIX/install. Idempotent.
#   bash scripts/setup_rig.sh [PREFIX]      # default PREFIX: .rig in the workspace
# Then run a node in it, e.g. the planner on a committed policy:
#   CGAIL_PREFIX=PREFIX scripts/ros2run cgail_planner planner_node --ros-args -p policy_path:=...
set -euo pipefail
WS="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$WS"
PY="${PYTHON:-python3}"
PREFIX="${1:-$WS/.rig}"
mkdir -p "$PREFIX"
PREFIX="$(cd "$PREFIX" && pwd)"
touch "$PREFIX/COLCON_IGNORE"  # a workspace build never crawls into it
export CGAIL_PREFIX="$PREFIX"
# the packages of a rig PC; colcon adds what they depend on (package.xml)
RIG_PACKAGES=(em_tracker pam_controller catheter_driver cgail_planner)

log() { printf '[setup_rig %3ds] %s\n' "$SECONDS" "$*" >&2; }

if ! "$PY" -c 'import sys, venv; assert sys.version_info >= (3, 10)' 2>/dev/null; then
    echo "[setup_rig] error: expected python3 >= 3.10 with the venv module, found: $("$PY" --version 2>&1 || echo none)." >&2
    exit 1
fi
if [ ! -x "$PREFIX/venv/bin/python" ]; then
    log "creating $PREFIX/venv with $("$PY" --version)"
    "$PY" -m venv "$PREFIX/venv"
fi
stamp="$PREFIX/venv/.requirements.sha256"
want=$(sha256sum requirements-rig.txt | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    log "installing requirements-rig.txt into $PREFIX/venv (first run: about a minute)"
    "$PREFIX/venv/bin/python" -m pip install --quiet --disable-pip-version-check -r requirements-rig.txt \
        2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2)
    echo "$want" > "$stamp"
else
    log "requirements up to date"
fi

# tf2_msgs (no wheel has it) with the rosidl tools, into PREFIX/install
bash scripts/build_interfaces.sh
# shellcheck disable=SC1091
source scripts/env.sh
log "colcon build --packages-up-to ${RIG_PACKAGES[*]}"
PYTHONWARNINGS="ignore:Unknown distribution option" \
    colcon --log-base "$PREFIX/log" build --build-base "$PREFIX/build" --install-base "$PREFIX/install" \
        --event-handlers console_cohesion- summary+ \
        --base-paths src --packages-up-to "${RIG_PACKAGES[@]}" --packages-skip tf2_msgs \
    2>&1 | grep -v -E '^(Starting >>>|Finished <<<)' >&2
if "$PREFIX/venv/bin/python" -c 'import torch' 2>/dev/null; then
    echo "[setup_rig] error: expected no torch in the lean install $PREFIX/venv, found it installed." >&2
    exit 1
fi
log "ready: CGAIL_PREFIX=$PREFIX scripts/ros2run <package> <node> ..."
