#!/usr/bin/env bash
# Idempotent workspace setup: .venv with the pinned requirements, then colcon build.
# Safe to re-run: pip runs only when requirements.txt changed, colcon build only when a file
# under src/ changed, and then incrementally.
#   bash scripts/setup.sh            # everything
#   CGAIL_SKIP_BUILD=1 bash scripts/setup.sh   # venv only
set -euo pipefail
WS="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$WS"
PY="${PYTHON:-python3}"

log() { printf '[setup %3ds] %s\n' "$SECONDS" "$*" >&2; }

# 1. Python >= 3.10 with venv (Debian: apt-get install python3 python3-venv).
if ! "$PY" -c 'import sys, venv; assert sys.version_info >= (3, 10)' 2>/dev/null; then
    echo "[setup] error: expected python3 >= 3.10 with the venv module, found: $("$PY" --version 2>&1 || echo none)." >&2
    echo "[setup] On Debian: sudo apt-get install python3 python3-venv" >&2
    exit 1
fi

# 2. The virtual environment.
if [ ! -x .venv/bin/python ]; then
    log "creating .venv with $("$PY" --version)"
    "$PY" -m venv .venv
fi

# 3. Pinned requirements, only when requirements.txt changed since the last install.
stamp=.venv/.requirements.sha256
want=$(sha256sum requirements.txt | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
    log "installing requirements.txt into .venv (first run: about 2 minutes)"
    # (the machine's pip config may name local indexes that do not exist: drop those warnings)
    .venv/bin/python -m pip install --quiet --disable-pip-version-check -r requirements.txt \
        2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2)
    echo "$want" > "$stamp"
else
    log "requirements up to date"
fi

# 3b. The docs site's tools (mkdocs, Material theme), the same way, from requirements-docs.txt.
dstamp=.venv/.requirements-docs.sha256
dwant=$(sha256sum requirements-docs.txt | cut -d' ' -f1)
if [ ! -f "$dstamp" ] || [ "$(cat "$dstamp")" != "$dwant" ]; then
    log "installing requirements-docs.txt into .venv (the docs site's tools)"
    .venv/bin/python -m pip install --quiet --disable-pip-version-check -r requirements-docs.txt \
        2> >(grep -v 'is ignored: it is neither a file nor a directory' >&2)
    echo "$dwant" > "$dstamp"
fi

# 4. Front-end assets for the GUI (three.js from the npm registry), if npm is present.
if [ -f src/cgail_gui/web/package.json ] && [ ! -d src/cgail_gui/web/node_modules ]; then
    if ! command -v npm >/dev/null 2>&1 && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 \
            && [ -z "${CGAIL_NO_APT:-}" ]; then
        log "installing npm from Debian for the GUI assets"
        (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq npm >/dev/null) \
            || log "warning: could not install npm"
    fi
    if command -v npm >/dev/null 2>&1; then
        log "installing GUI assets with npm"
        (cd src/cgail_gui/web && npm ci --no-audit --no-fund --silent)
    else
        log "warning: npm not found; the GUI needs it (Debian: apt-get install npm)"
    fi
fi

# 5. colcon build (incremental, symlinked so edits to python sources need no rebuild).
if [ -z "${CGAIL_SKIP_BUILD:-}" ]; then
    # shellcheck disable=SC1091
    source scripts/env.sh
    # A build from before cgail_planner was split into packages (issue 32) keeps the tools'
    # console scripts (cgail, phantom_node, gui_node, ...) in install/cgail_planner, where they
    # shadow those of the packages that own them now: build that package again from scratch.
    if [ -e install/cgail_planner/lib/cgail_planner/cgail ]; then
        log "removing the build of cgail_planner from before the package split"
        rm -rf build/cgail_planner install/cgail_planner
    fi
    # colcon build only when a file under src/ (or the build scripts, or the venv's
    # requirements) was added, removed or changed since the last successful build: with
    # --symlink-install an edit to a module needs no build, but colcon still spends ~10 s
    # checking 11 packages, which every run of the main job (scripts/demo.sh) would pay.
    build_stamp=build/.cgail-sources.sha256
    sources=$({ find src -name __pycache__ -prune -o -type f -printf '%p %s %T@\n'
                stat -c '%n %s %Y' scripts/setup.sh scripts/build_interfaces.sh
                cat .venv/.requirements.sha256 2>/dev/null || true; } | LC_ALL=C sort | sha256sum)
    sources=${sources%% *}
    if [ -f "$build_stamp" ] && [ "$(cat "$build_stamp")" = "$sources" ] \
            && [ -f install/setup.bash ]; then
        log "colcon build: nothing under src/ changed since the last build"
    else
        rm -f "$build_stamp"
        # The interface packages (tf2_msgs: no wheel has it) first, with the rosidl tools.
        bash scripts/build_interfaces.sh
        log "colcon build"
        # colcon reads tests_require to find pytest; setuptools warns it is unknown: silence
        # that.
        PYTHONWARNINGS="ignore:Unknown distribution option" \
            colcon --log-base log build --symlink-install --event-handlers console_cohesion- \
                summary+ --packages-skip tf2_msgs \
            2>&1 | grep -v -E '^(Starting >>>|Finished <<<)' >&2
        echo "$sources" > "$build_stamp"
    fi
    # 6. numba kernels and built-in anatomies into their disk caches (~1 min on a fresh clone,
    #    a few seconds after that), so no test deadline or first trial pays the compile.
    log "warm-up: numba kernels and anatomy caches"
    # shellcheck disable=SC1091
    source scripts/env.sh  # again: install/setup.bash exists only now on a fresh clone
    python -m cgail_rig.warmup >&2
fi
log "ready"
