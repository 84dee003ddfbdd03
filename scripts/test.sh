#!/usr/bin/env bash
# Set up if needed, then run the whole test suite: lint (ruff), types (mypy on every module of
# the packages and on the bench scripts), every package's tests through colcon, the
# cross-package tests in test/, and the strict build of the docs site (mkdocs.yml).
# Exits non-zero on any failure.  Extra arguments go to the final pytest run of test/.
#   bash scripts/test.sh            # default (fast) suite
#   CGAIL_SLOW=1 bash scripts/test.sh   # also the tests marked slow
set -euo pipefail
WS="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$WS"
start=$(date +%s)
bash scripts/setup.sh

# The GUI's browser test needs Debian's chromium (never a downloaded browser). Install it when
# we can (root + apt); otherwise that one test is skipped with the install command.
if ! command -v chromium >/dev/null 2>&1 && [ -z "${CGAIL_NO_APT:-}" ] \
        && [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "[test] installing chromium from Debian for the GUI browser test"
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium \
        >/dev/null) || echo "[test] warning: could not install chromium; the browser test will skip"
fi

# shellcheck disable=SC1091
source scripts/env.sh
# A DDS domain of this run's own, held (flock) until the run ends, so parallel runs and
# simulated sessions on one machine never see each other (cgail_rig/domain.py).
if [ -z "${ROS_DOMAIN_ID:-}" ]; then
    lock_dir="${XDG_RUNTIME_DIR:-/tmp}/cgail_ros_domains"
    mkdir -p "$lock_dir"
    for id in $(seq 1 101); do
        exec {domain_fd}>>"$lock_dir/$id.lock"
        if flock -n "$domain_fd"; then
            if [ -z "$(python -m cgail_rig.domain --probe "$id")" ]; then
                echo "$$" > "$lock_dir/$id.lock"
                export ROS_DOMAIN_ID=$id
                break
            fi
        fi
        exec {domain_fd}>&-
    done
    if [ -z "${ROS_DOMAIN_ID:-}" ]; then
        echo "[test] error: expected a free ROS domain in 1..101, found none" >&2
        exit 1
    fi
fi
echo "[test] ROS_DOMAIN_ID=$ROS_DOMAIN_ID ROS_AUTOMATIC_DISCOVERY_RANGE=$ROS_AUTOMATIC_DISCOVERY_RANGE"

marker=()
if [ -n "${CGAIL_SLOW:-}" ]; then marker=(-m ""); fi

echo "[test] ruff"
ruff check src test bench
echo "[test] mypy (every module of the packages, nodes included, and the bench scripts)"
# (every ament_python package under src/: its directory on MYPYPATH, its module checked)
pkgs=(cgail_node_utils em_tracker pam_controller catheter_driver cgail_sim cgail_planner
      cgail_bags cgail_gui cgail_learning cgail_patient cgail_rig)
modules=()
for p in "${pkgs[@]}"; do modules+=("src/$p/$p"); done
MYPYPATH="$(printf 'src/%s:' "${pkgs[@]}")" \
    mypy --config-file pyproject.toml "${modules[@]}" bench/*.py \
    src/cgail_learning/test/fixtures/make_policies.py

echo "[test] colcon test"
rm -rf build/*/test_results
pytest_args=(-q -rfE)
if [ -n "${CGAIL_SLOW:-}" ]; then pytest_args+=(-m ""); fi
colcon --log-base log test --executor sequential --event-handlers console_direct+ --packages-skip tf2_msgs \
    --pytest-args "${pytest_args[@]}"
# colcon test exits 0 even when tests fail: test-result is what fails.
colcon test-result --verbose --test-result-base build

echo "[test] cross-package tests (test/)"
python -m pytest test -q -rfE "${marker[@]}" "$@"

echo "[test] docs site (mkdocs build --strict)"
# A broken link, anchor or nav entry fails the build; the site goes to a temporary directory.
site_dir=$(mktemp -d)
# (not --quiet: it silences the warnings that --strict counts)
NO_MKDOCS_2_WARNING=1 mkdocs build --strict -d "$site_dir" 2>&1 | { grep -v '^INFO ' || true; }
rm -rf "$site_dir"

echo "[test] all passed in $(( $(date +%s) - start )) s"
