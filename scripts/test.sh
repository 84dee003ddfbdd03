#!/usr/bin/env bash
# Set up if needed, then run the whole test suite: lint (ruff), types (mypy on every module of
# the packages and on the bench scripts), every package's tests through colcon, and the
# cross-package tests in test/.
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
# simulated sessions on one machine never see each other (cgail_planner/system/domain.py).
if [ -z "${ROS_DOMAIN_ID:-}" ]; then
    lock_dir="${XDG_RUNTIME_DIR:-/tmp}/cgail_ros_domains"
    mkdir -p "$lock_dir"
    for id in $(seq 1 101); do
        exec {domain_fd}>>"$lock_dir/$id.lock"
        if flock -n "$domain_fd"; then
            if [ -z "$(python -m cgail_planner.system.domain --probe "$id")" ]; then
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
MYPYPATH="src/cgail_planner:src/em_tracker:src/pam_controller:src/catheter_driver:src/cgail_node_utils" \
    mypy --config-file pyproject.toml src/cgail_planner/cgail_planner src/em_tracker/em_tracker \
    src/pam_controller/pam_controller src/catheter_driver/catheter_driver \
    src/cgail_node_utils/cgail_node_utils bench/*.py \
    src/cgail_planner/test/fixtures/make_policies.py

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

echo "[test] all passed in $(( $(date +%s) - start )) s"
