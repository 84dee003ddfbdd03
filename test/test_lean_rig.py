"""The lean rig install (``bash scripts/setup_rig.sh``): a fresh venv without torch holding only
the device packages and the planner, which imports everything it installed and runs
``planner_node`` on a committed policy in a short simulated trial (issue 32).

The install goes to ``$CGAIL_RIG_PREFIX`` (default: ``.rig`` in the workspace; the script is
idempotent, so a second run only checks it). Every command in the lean install runs with a
clean environment (no variable of the full workspace's venv or install leaks in), in this run's
ROS domain, localhost only.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
import re
import signal
import subprocess
import sys

import pytest
from test_torch_free import FORBIDDEN, LEAN_PACKAGES

ROOT = Path(__file__).resolve().parents[1]

#: Distributions of the workspace a rig never needs.
TRAINING_ONLY = ('torch', 'tqdm', 'ray', 'nibabel', 'pynrrd', 'scikit-image', 'websockets',
                 'pyigtl', 'foxglove-sdk', 'pytest', 'ruff', 'mypy')


def pins(path: Path) -> dict[str, str | None]:
    """``{distribution (lower case, extras dropped): pinned version or None}`` of a file."""
    found = {}
    for line in path.read_text().splitlines():
        line = line.split('#', 1)[0].strip()
        if not line:
            continue
        m = re.fullmatch(r'([A-Za-z0-9_.-]+)(\[[^\]]*\])?(==([^\s;]+))?', line)
        assert m, f'{path.name}: expected name[==version], found {line!r}'
        found[m.group(1).lower()] = m.group(4)
    return found


def test_rig_requirements_pin_what_the_workspace_pins() -> None:
    rig, full = pins(ROOT / 'requirements-rig.txt'), pins(ROOT / 'requirements.txt')
    assert rig, 'requirements-rig.txt pins nothing'
    for name, version in rig.items():
        assert version, f'requirements-rig.txt: expected {name}==version, found no pin'
        assert name in full, f'requirements-rig.txt pins {name}, which requirements.txt lacks'
        assert version == full[name], (f'{name}: requirements-rig.txt pins {version}, '
                                       f'requirements.txt {full[name]}')
    assert not set(rig) & set(TRAINING_ONLY), f'training-only: {set(rig) & set(TRAINING_ONLY)}'


def lean_env(prefix: Path) -> dict[str, str]:
    """A clean environment for the lean install: nothing of the full workspace's."""
    env = {'HOME': os.environ['HOME'], 'PATH': '/usr/local/bin:/usr/bin:/bin',
           'LANG': 'C.UTF-8', 'CGAIL_PREFIX': str(prefix)}
    for key in ('ROS_DOMAIN_ID', 'CGAIL_PLANNER_NO_DISK_CACHE', 'NPY_DISABLE_CPU_FEATURES',
                'TMPDIR', 'XDG_RUNTIME_DIR'):
        if key in os.environ:
            env[key] = os.environ[key]
    return env


IMPORT_ALL = f"""
import importlib, importlib.util, pkgutil, sys
from pathlib import Path
names = {sorted(LEAN_PACKAGES)!r}
count = 0
for name in names:
    pkg = importlib.import_module(name)
    for info in pkgutil.walk_packages(pkg.__path__, name + '.'):
        if info.name.rsplit('.', 1)[-1] == 'testing':
            continue  # (test helpers shipped in the package: pytest fixtures, not the rig's)
        importlib.import_module(info.name)
        count += 1
import tf2_msgs.msg
for name in {[*FORBIDDEN, 'cgail_learning', 'cgail_rig', 'cgail_patient']!r}:
    assert importlib.util.find_spec(name) is None, f'{{name}} is installed in the lean venv'
    assert name not in sys.modules, f'{{name}} was imported'
print(count)
"""


@pytest.mark.timeout(1800)
def test_lean_rig_install_imports_everything_and_runs_planner_node() -> None:
    prefix = Path(os.environ.get('CGAIL_RIG_PREFIX', ROOT / '.rig'))
    env = lean_env(prefix)
    setup = subprocess.run(['bash', str(ROOT / 'scripts/setup_rig.sh'), str(prefix)], cwd=ROOT,
                           env=env, capture_output=True, text=True, timeout=1500)
    assert setup.returncode == 0, f'setup_rig.sh failed:\n{setup.stderr[-4000:]}'
    installed = sorted(p.name for p in (prefix / 'install').iterdir() if p.is_dir())
    assert installed == sorted([*LEAN_PACKAGES, 'tf2_msgs']), installed

    def ws(*args: str, **kw) -> subprocess.CompletedProcess:
        return subprocess.run([str(ROOT / 'scripts/ws'), *args], cwd=ROOT, env=env,
                              capture_output=True, text=True, **kw)

    imported = ws('python', '-c', IMPORT_ALL, timeout=600)
    assert imported.returncode == 0, imported.stderr[-4000:]
    assert int(imported.stdout.split()[-1]) > 50, imported.stdout

    policy = ws('python', '-c', 'import cgail_planner, pathlib; print(pathlib.Path('
                'cgail_planner.__file__).parent / "models" / "cgail_default_static.onnx")',
                timeout=120).stdout.strip()
    assert policy.startswith(str(prefix)) and Path(policy).is_file(), policy
    log = prefix / 'planner_node.log'
    with log.open('w') as out:
        planner = subprocess.Popen(
            [str(ROOT / 'scripts/ros2run'), 'cgail_planner', 'planner_node', '--ros-args',
             '-p', f'policy_path:={policy}', '-p', 'diagnostics_period_s:=0.2'],
            cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        trial = ws('python', str(ROOT / 'test/lean_rig_trial.py'), timeout=900)
    finally:
        os.killpg(planner.pid, signal.SIGINT)
        try:
            planner.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(planner.pid, signal.SIGKILL)
            planner.wait()
    print(trial.stdout, file=sys.stderr)
    assert trial.returncode == 0, (f'{trial.stdout[-3000:]}\n{trial.stderr[-3000:]}\n'
                                   f'planner_node:\n{log.read_text()[-3000:]}')
    summary = json.loads(trial.stdout.strip().splitlines()[-1])
    assert summary['guided_poses'] == summary['path_points'] > 100
    assert summary['torch_loaded'] is False
    assert 'cgail path planned' in log.read_text()
