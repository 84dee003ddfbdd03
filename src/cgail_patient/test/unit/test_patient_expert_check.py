"""The expert check of validate_anatomy: the scripted expert drives whole episodes to every
standard target, static and dynamic; a target it cannot reach refuses the anatomy, and the
error names the target, the mode, the starts tried and why each failed."""

from __future__ import annotations

import dataclasses
from pathlib import Path
import re

import numpy as np
import pytest
import yaml

from cgail_learning.expert import ScriptedExpert
from cgail_patient.prepare_cli import main
from cgail_patient.synthetic import make_synthetic_ct, SyntheticCTConfig
from cgail_patient.validate import (
    expert_success,
    run_expert_trial,
    validate_anatomy,
)
from cgail_sim.anatomy import build_anatomy
from cgail_sim.config import EnvConfig
import cgail_sim.env as env_mod
from cgail_sim.scenarios import World


def _row(v, name):
    return next(c for c in v.checks if c.name == name)


def _moved_behind_the_wall(world: World, k: int) -> World:
    """``world`` with its target ``k`` moved 10 mm outside the lumen, behind its wall vertex."""
    anatomy, sc = world.anatomy, world.scenarios
    t = sc.targets[k]
    rest = np.asarray(anatomy.vertices[t.vertex])
    position = rest + 0.010 * np.asarray(anatomy.mesh.vertex_normals[t.vertex])
    assert not anatomy.contains(position[None])[0]
    moved = dataclasses.replace(t, position=position, offset=position - rest)
    targets = tuple(moved if j == k else x for j, x in enumerate(sc.targets))
    return World(anatomy, world.centerlines, dataclasses.replace(sc, targets=targets))


def _target_behind_the_wall(monkeypatch: pytest.MonkeyPatch, k: int) -> None:
    """Every env built from now on has its target ``k`` behind the wall; the geometric checks
    still see the true targets, so only driving can find it."""
    real = env_mod.load_world
    monkeypatch.setattr(env_mod, "load_world",
                        lambda *args: _moved_behind_the_wall(real(*args), k))


def test_expert_reaches_every_standard_target_in_the_rigid_aorta() -> None:
    v = validate_anatomy(build_anatomy("default"), wall=False, expert=True,
                         expert_modes=("static",))
    row = _row(v, "expert static")
    assert row.status == "ok", row.message
    assert row.value.startswith("5/5 targets reached (5 episodes, ")
    trials = v.expert_trials
    assert [(t.target, t.start) for t in trials] == [(0, 0), (1, 1), (2, 2), (3, 0), (4, 1)]
    for t in trials:
        assert t.outcome == "success" and t.detail == ""
        assert 100 < t.steps < 2000
        assert t.final_distance_mm < 10.0 and t.closest_mm <= t.final_distance_mm + 1e-6
        assert t.max_wall_mm == 0.0
    assert v.errors == []


def test_dynamic_trial_is_a_whole_episode_in_the_beating_wall() -> None:
    env = env_mod.CatheterNavEnv(EnvConfig(mode="dynamic"))
    t = run_expert_trial(env, ScriptedExpert(env), 2, 2)
    assert (t.mode, t.start, t.target, t.outcome) == ("dynamic", 2, 2, "success")
    assert t.steps > 100 and t.final_distance_mm < 10.0
    # The heartbeat moves the root by ~10 mm; the catheter body pushes the wall within bounds.
    assert 5.0 < t.max_wall_mm < 25.0


def test_unreachable_target_is_an_error_naming_it(monkeypatch: pytest.MonkeyPatch) -> None:
    _target_behind_the_wall(monkeypatch, 3)
    v = validate_anatomy(build_anatomy("default"), wall=False, expert=True)
    row = _row(v, "expert static")
    assert row.status == "error"
    assert row.value.startswith("4/5 targets reached (7 episodes, ")
    assert row.message.startswith("expected the scripted expert to reach every standard "
                                  "target, found target 3 ((")
    assert "mm from the annulus centre, " in row.message
    assert " not reached in static mode: from start 0: " in row.message
    assert "; from start 1: " in row.message and "; from start 2: " in row.message
    assert "\n" not in row.message
    failed = [t for t in v.expert_trials if t.target == 3]
    assert [t.start for t in failed] == [0, 1, 2]
    for t in failed:
        assert t.outcome in ("collision", "timeout", "exited")
        assert t.detail in row.message
    # the other targets are reached from their own starts
    assert [(t.target, t.start) for t in v.expert_trials if t.outcome == "success"] == [
        (0, 0), (1, 1), (2, 2), (4, 1)]
    # the dynamic drive is not run on top of a refused lumen
    assert _row(v, "expert dynamic").message == "not run: fix the errors above first"


@pytest.mark.slow
def test_prepare_anatomy_refuses_an_unreachable_target(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    ct = make_synthetic_ct(SyntheticCTConfig(spacing_mm=(1.6, 1.6, 2.0),
                                             descending_length_mm=170.0))
    paths = ct.write(tmp_path)
    _target_behind_the_wall(monkeypatch, 3)
    out = tmp_path / "prepared"
    assert main([str(paths["aorta"]), "--lv", str(paths["lv"]), "--out", str(out),
                 "--voxel-mm", "1.2", "--target-vertices", "1500", "--no-wall-check"]) == 1
    errors = [line for line in capsys.readouterr().err.splitlines() if ": error: " in line]
    assert errors[0].startswith(
        "cgail prepare-anatomy: error: expert static: expected the scripted expert to reach every "
        "standard target, found target 3 ((")
    assert "mm from the annulus centre, " in errors[0]
    assert " not reached in static mode: from start 0: " in errors[0]
    assert "; from start 1: " in errors[0] and "; from start 2: " in errors[0]
    # the dynamic drive is not run on top of a refused lumen
    assert errors[1:] == ["cgail prepare-anatomy: error: expert dynamic: not run: fix the errors "
                          "above first"]
    # The report, the render and the rejected lumen are written; the table says why.
    for name in ("report.md", "render.png", "prepare.yaml", "lumen.rejected.stl"):
        assert (out / name).is_file(), name
    assert not (out / "lumen.stl").exists()
    report = (out / "report.md").read_text()
    assert "| expert static | **ERROR** | 4/5 targets reached (7 episodes, " in report
    rows = [line for line in report.splitlines() if line.startswith("| static | 3 | ")]
    assert [row.split(" | ")[4] for row in rows] == ["0", "1", "2"]  # the starts tried
    record = yaml.safe_load((out / "prepare.yaml").read_text())
    failed = [t for t in record["expert_check"] if t["target"] == 3]
    assert [t["outcome"] for t in failed] != [] and all(
        t["outcome"] in ("collision", "timeout", "exited") and t["detail"] in errors[0]
        for t in failed)
    assert record["usable"] is False


def test_collision_detail_names_distance_and_step(monkeypatch: pytest.MonkeyPatch) -> None:
    _target_behind_the_wall(monkeypatch, 3)
    env = env_mod.CatheterNavEnv(EnvConfig())
    t = run_expert_trial(env, ScriptedExpert(env), 0, 3)
    assert t.outcome == "collision", t
    m = re.fullmatch(r"collision (\d+) mm from the target at step (\d+) \(\d+\.\d N, "
                     r"\d+\.\d mm into the wall\), \d+ mm along the centreline"
                     r"(, where it bends with a \d+ mm radius)? in a lumen of \d+ mm radius",
                     t.detail)
    assert m, t.detail
    assert int(m[2]) == t.steps < 2000
    assert abs(int(m[1]) - t.final_distance_mm) <= 0.5


class _Retract:
    """Pulls the catheter back: out through the descending cut."""

    def reset(self, seed: int | None) -> None:
        pass

    def act(self) -> np.ndarray:
        return np.array([0.0, 0.0, -1.0], dtype=np.float32)


def test_exit_detail_names_the_cut() -> None:
    env = env_mod.CatheterNavEnv(EnvConfig())
    t = run_expert_trial(env, _Retract(), 0, 1)
    assert t.outcome == "exited", t
    assert t.detail == (f"exited through the descending cut at step {t.steps}, "
                        f"{t.final_distance_mm:.0f} mm from the target")


def test_simulation_fault_ends_the_trial_and_refuses(monkeypatch: pytest.MonkeyPatch) -> None:
    # A wall whose fault bound (5 mm) the heartbeat itself exceeds: the first dynamic episode
    # ends as a simulation fault, which refuses the anatomy without trying other starts.
    monkeypatch.setattr(env_mod, "DYNAMIC_PBD_CONFIG",
                        dataclasses.replace(env_mod.DYNAMIC_PBD_CONFIG, max_displacement=0.005))
    v = validate_anatomy(build_anatomy("default"), wall=False, expert=True,
                         expert_modes=("dynamic",))
    row = _row(v, "expert dynamic")
    assert row.status == "error"
    (t,) = v.expert_trials
    assert (t.outcome, t.start, t.target) == ("simulation fault", 0, 0)
    assert t.detail.startswith(f"simulation fault at step {t.steps} (")
    # The env resets a faulted wall for that last step's sensing: the displacement that
    # tripped the bound is the one the fault's message names.
    import re
    away = re.search(r"([\d.]+) mm away", t.detail)
    assert away and float(away.group(1)) > 5.0, t.detail
    assert "target 0 ((" in row.message and "not reached in dynamic mode: from start 0: " \
        "simulation fault at step " in row.message


def test_bad_modes_are_refused_before_any_work() -> None:
    with pytest.raises(ValueError, match=r"expert_modes: expected modes among 'static' and "
                                         r"'dynamic', found \['beating'\]"):
        validate_anatomy(build_anatomy("default"), expert=True, expert_modes=("beating",))
    with pytest.raises(ValueError, match="method: expected 'expert' or 'follower', found 'rrt'"):
        expert_success("default", method="rrt")


def test_expert_success_on_an_unseen_target_set() -> None:
    table = expert_success("default", sets=(1,), modes=("static",), method="follower",
                           trials=3)
    assert table.method == "follower"
    assert len(table.trials["static"][1]) == 3
    assert 0.0 <= table.rate("static") <= 1.0
    text = table.markdown()
    assert text.splitlines()[0] == "| follower | set 1 | all |"
    assert text.splitlines()[2].startswith("| static | ")



@pytest.mark.slow
def test_prepared_synthetic_patient_passes_the_whole_check(tmp_path: Path) -> None:
    ct = make_synthetic_ct(SyntheticCTConfig(spacing_mm=(1.6, 1.6, 2.0),
                                             descending_length_mm=170.0))
    paths = ct.write(tmp_path)
    out = tmp_path / "prepared"
    assert main([str(paths["aorta"]), "--lv", str(paths["lv"]), "--out", str(out),
                 "--voxel-mm", "1.2", "--target-vertices", "1500"]) == 0
    record = yaml.safe_load((out / "prepare.yaml").read_text())
    trials = record["expert_check"]
    assert [(t["mode"], t["target"], t["start"], t["outcome"]) for t in trials] == [
        (mode, k, k % 3, "success") for mode in ("static", "dynamic") for k in range(5)]
    assert all(0.0 < t["max_wall_displacement_mm"] < 25.0 for t in trials
               if t["mode"] == "dynamic")
    report = (out / "report.md").read_text()
    assert "| expert static | ok | 5/5 targets reached (5 episodes, " in report
    assert "| expert dynamic | ok | 5/5 targets reached (5 episodes, " in report
    assert "## Scripted expert to every standard target" in report
