"""The reward table of the paper (Table I), one test per event with exact values."""

import numpy as np
import pytest

from cgail_sim.reward import (
    bending_event,
    compute_reward,
    non_minor_collision,
    reached_target,
    RewardConfig,
    StepEvents,
    update_waypoints,
)

CFG = RewardConfig()


def events(**kw: object) -> StepEvents:
    base = dict(collision=[False], exited=[False], success=[False], new_waypoints=[0],
                bending=[False])
    base.update(kw)
    return StepEvents(**{k: np.asarray(v) for k, v in base.items()})


def test_table_values() -> None:
    assert (CFG.r_obst, CFG.r_exit, CFG.r_target) == (-1.0, -1.0, 1.0)
    assert (CFG.r_step, CFG.r_centerline, CFG.r_bending) == (-1e-5, 0.05, 1e-5)
    assert CFG.epsilon == 0.010
    assert CFG.minor_force == 0.8


@pytest.mark.parametrize(
    ("kw", "reward", "terminated"),
    [
        ({}, -1e-5, False),
        ({"collision": [True]}, -1.0 - 1e-5, True),
        ({"exited": [True]}, -1.0 - 1e-5, True),
        ({"success": [True]}, 1.0 - 1e-5, True),
        ({"new_waypoints": [1]}, 0.05 - 1e-5, False),
        ({"new_waypoints": [3]}, 0.15 - 1e-5, False),
        ({"bending": [True]}, 0.0, False),
        ({"collision": [True], "success": [True]}, -1.0 - 1e-5, True),  # obst wins
        ({"exited": [True], "success": [True]}, -1.0 - 1e-5, True),  # exit wins
        ({"success": [True], "new_waypoints": [2], "bending": [True]}, 1.1, True),
    ],
)
def test_reward_per_event(kw: dict, reward: float, terminated: bool) -> None:
    terms, term = compute_reward(events(**kw), CFG)
    assert terms.total[0] == pytest.approx(reward, abs=1e-15)
    assert bool(term[0]) is terminated


def test_terms_split() -> None:
    terms, _ = compute_reward(events(success=[True], new_waypoints=[1], bending=[True]), CFG)
    assert (terms.end[0], terms.step[0], terms.centerline[0], terms.bending[0]) == (
        1.0, -1e-5, 0.05, 1e-5)


@pytest.mark.parametrize(
    ("force", "penetration", "non_minor"),
    [(0.0, 0.0, False), (0.79, 0.0, False), (0.8, 0.0, True), (0.1, 1e-4, True),
     (2.0, 0.0, True)],
)
def test_collision_classes(force: float, penetration: float, non_minor: bool) -> None:
    assert bool(non_minor_collision(np.array([force]), np.array([penetration]), CFG)[0]) \
        is non_minor


def test_success_distance() -> None:
    tips = np.array([[0.0, 0.0, 0.0099], [0.0, 0.0, 0.0101]])
    assert reached_target(tips, np.zeros((2, 3)), CFG).tolist() == [True, False]


def test_waypoints_pay_once() -> None:
    wps = np.array([[[0.0, 0.0, z] for z in (0.0, 0.005, 0.010, 0.1)]])
    reached = np.zeros((1, 4), dtype=bool)
    assert update_waypoints(np.array([[0.0, 0.0, 0.0025]]), wps, reached, CFG).tolist() == [2]
    assert update_waypoints(np.array([[0.0, 0.0, 0.0025]]), wps, reached, CFG).tolist() == [0]
    assert update_waypoints(np.array([[0.0, 0.0, 0.0070]]), wps, reached, CFG).tolist() == [1]
    assert reached.tolist() == [[True, True, True, False]]


def test_bending_threshold() -> None:
    lim = np.array([0.01, 0.01, 0.01, 0.0])
    alpha = np.array([0.0091, 0.0089, 0.0, 0.0])
    gamma = np.array([0.0, 0.0, -0.0095, 0.0])
    assert bending_event(alpha, gamma, lim, CFG).tolist() == [True, False, True, False]


@pytest.mark.parametrize(
    ("field", "value"),
    [("r_obst", 0.5), ("r_target", 2.0), ("epsilon", 0.0), ("bend_threshold", 1.5),
     ("minor_force", float("inf"))],
)
def test_config_rejects(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=f"{field} must be in"):
        RewardConfig(**{field: value})
