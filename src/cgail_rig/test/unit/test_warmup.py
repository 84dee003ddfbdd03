"""The setup's cache warm-up runs every kernel it promises to compile, in order."""

from __future__ import annotations

from cgail_rig.warmup import main


def test_warmup_runs_env_and_planner_kernels(capsys) -> None:
    assert main(['--anatomies', 'default']) == 0
    out = capsys.readouterr().out
    for step in ("anatomy 'default'", 'static environment kernels',
                 'dynamic environment kernels', 'planner rollout kernel', 'caches ready'):
        assert step in out
