# shellcheck shell=bash
# The one place that sets up the environment of every process in this workspace
# (setup, tests, CI, demos, benchmarks, nodes started by hand). Source it:
#     source scripts/env.sh
# or prefix a command with scripts/ws:   scripts/ws python bench/bench_sim.py
#
# DDS discovery must never leave this machine: ROS 2 Jazzy multicasts to the LAN
# unless ROS_AUTOMATIC_DISCOVERY_RANGE is LOCALHOST. We force it (not default it):
# a rig that really needs the network must edit this line on purpose.
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
export ROS_STATIC_PEERS=""
export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
# ROS_DOMAIN_ID is left as the caller set it (unset: ROS's default, domain 0). The simulated
# session picks a free domain of its own unless it is set, and refuses a domain where a rig's
# device nodes answer (cgail_rig/domain.py); the test command holds one per run.
# Headless defaults for matplotlib / SDL (gamepad) so nothing opens a window.
export MPLBACKEND="${MPLBACKEND:-Agg}"
export SDL_VIDEODRIVER="${SDL_VIDEODRIVER:-dummy}"
export PYTHONUNBUFFERED=1

CGAIL_WS="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export CGAIL_WS
# The full workspace is .venv + install/; a lean rig install (scripts/setup_rig.sh) is
# $CGAIL_PREFIX/venv + $CGAIL_PREFIX/install.
if [ -n "${CGAIL_PREFIX:-}" ]; then
    _cgail_venv="$CGAIL_PREFIX/venv"
    _cgail_install="$CGAIL_PREFIX/install"
else
    _cgail_venv="$CGAIL_WS/.venv"
    _cgail_install="$CGAIL_WS/install"
fi
if [ -f "$_cgail_venv/bin/activate" ]; then
    # shellcheck disable=SC1091
    source "$_cgail_venv/bin/activate"
fi
if [ -f "$_cgail_install/setup.bash" ]; then
    # colcon's setup scripts reference unset variables; relax -u while sourcing.
    _cgail_u=$(set +o | grep nounset)
    set +u
    # shellcheck disable=SC1091
    source "$_cgail_install/setup.bash"
    eval "$_cgail_u"
fi
# Every package's executables (install/<pkg>/lib/<pkg>, where `ros2 run` looks; colcon's setup
# does not put them on PATH) at the end of PATH, so that `scripts/ws cgail make-demos ...` works
# without ros2cli (scripts/ros2run <pkg> <executable> is the `ros2 run` form).
for _cgail_pkg in "$_cgail_install"/*/; do
    _cgail_bin="${_cgail_pkg}lib/$(basename "$_cgail_pkg")"
    if [ -d "$_cgail_bin" ] && [[ ":$PATH:" != *":$_cgail_bin:"* ]]; then
        PATH="$PATH:$_cgail_bin"
    fi
done
unset _cgail_pkg _cgail_bin _cgail_venv _cgail_install
export PATH
