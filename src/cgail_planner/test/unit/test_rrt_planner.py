"""The curvature-constrained RRT (core/rrt_planner.py) through the Planner: curvature, clearance,
start and goal, seeding, the iteration budget and the time limit, and one-line errors.

Every test that asserts a result bounds the search by the iteration budget with a generous
time limit (:data:`TIME_LIMIT_S`), so its outcome does not depend on the machine's speed or load.
"""

from dataclasses import replace
import math

import numpy as np
import pytest

from cgail_planner.core.errors import InvalidInputError, NoPathError
from cgail_planner.core.path_fit import discrete_curvature
from cgail_planner.core.planner import model_world_from_sim, Planner, PlannerConfig
from cgail_planner.core.rrt_planner import RrtConfig
from cgail_sim.ftl_model import CatheterConfig
from cgail_sim.wall import StaticWall
from cgail_sim.worlds import load_world

#: Allowance of the discrete (Menger) curvature of the 0.5 mm curve samples over 1 / r_min
#: (rounding only: the planner asks OMPL for 5% more radius than r_min, RADIUS_FACTOR).
CURVATURE_ALLOWANCE = 1.001
#: The same for the published path, linearly resampled every 1 mm from those samples: a point
#: 1 um off the curve (the chord error) moves the discrete curvature of 1 mm spacing by ~8 /m,
#: so up to 2% over 1 / r_min was measured there although the curve is within it.
PATH_CURVATURE_ALLOWANCE = 1.03
#: Time limit of the tests that assert a result: far beyond what the iteration budget takes.
TIME_LIMIT_S = 60.0


def make_planner(anatomy: str = 'default', **rrt) -> Planner:
    world = load_world(anatomy)
    config = PlannerConfig(planner_type='rrt',
                           rrt=RrtConfig(**{'time_limit_s': TIME_LIMIT_S, **rrt}))
    return Planner(config, model_world_from_sim(world), StaticWall(world.anatomy), None)


@pytest.fixture(scope='module')
def world():
    return load_world('default')


@pytest.fixture(scope='module')
def planner() -> Planner:
    return make_planner()


@pytest.mark.parametrize(('start', 'target'), [(0, 0), (2, 3)])
def test_path_respects_curvature_clearance_start_and_goal(planner, world, start, target) -> None:
    st, goal = world.scenarios.starts[start], world.scenarios.targets[target].position
    result = planner.plan(st.position, st.rotation, goal)
    rrt, cat = planner.rrt, planner.config.catheter
    assert result.planner_type == 'rrt'
    assert 1 <= result.iterations <= planner.config.rrt.max_iterations
    assert rrt is not None and rrt.r_min == pytest.approx(cat.segment_length / cat.theta_max)
    curve, path = result.raw, result.path
    # curvature of the curves (sampled every 0.5 mm) and of the published path
    assert discrete_curvature(curve).max() <= CURVATURE_ALLOWANCE / rrt.r_min
    assert discrete_curvature(path).max() <= PATH_CURVATURE_ALLOWANCE / rrt.r_min
    # every point inside the lumen with the catheter radius plus the margin from the wall
    need = cat.radius + planner.config.rrt.clearance_margin
    assert rrt.clearance(curve).min() >= need - 1e-6
    assert rrt.clearance(path).min() >= need - 1e-6
    assert world.anatomy.contains(path).all()
    # starts at the tip along its heading, ends at the goal (these targets have the clearance)
    assert path[0] == pytest.approx(st.position, abs=1e-9)
    first = (curve[1] - curve[0]) / np.linalg.norm(curve[1] - curve[0])
    assert float(first @ st.rotation[:, 1]) > math.cos(math.radians(1.0))
    assert np.linalg.norm(path[-1] - goal) <= 0.5 * planner.config.goal_tolerance
    assert np.linalg.norm(np.diff(path, axis=0), axis=1) == pytest.approx(
        planner.config.path_spacing, rel=0.05)


def test_same_seed_same_path_other_seed_other_path(world) -> None:
    st, goal = world.scenarios.starts[1], world.scenarios.targets[2].position

    def plan(seed: int):
        rrt = make_planner(seed=seed).rrt
        assert rrt is not None
        return rrt.plan(st.position, st.rotation, goal, 0.01)

    a, b, c = plan(3), plan(3), plan(4)
    # the iteration budget, not the clock, ends the search: the same iterations every run
    assert a.iterations == b.iterations <= RrtConfig().max_iterations
    # (same machine: equal to rounding; across CPUs compare properties, not bits)
    assert a.points.shape == b.points.shape and np.abs(a.points - b.points).max() < 1e-9
    assert a.points.shape != c.points.shape or np.abs(a.points - c.points).max() > 1e-4


def test_no_path_in_the_time_limit_is_one_clear_line(world) -> None:
    st, goal = world.scenarios.starts[0], world.scenarios.targets[0].position
    # (0.1 ms cannot hold the iteration budget: this cannot pass by finding a path)
    planner = make_planner(time_limit_s=1e-4)
    with pytest.raises(NoPathError, match=r'^rrt found no path within time_limit_s 0\.0001 s '
                                          r'\(\d+ iterations, \d+ nodes, seed 0\)$') as info:
        planner.plan(st.position, st.rotation, goal)
    assert '\n' not in str(info.value) and info.value.reason == 'time_limit'
    assert info.value.step is not None and info.value.step < RrtConfig().max_iterations


def test_no_path_in_the_iteration_budget_is_one_clear_line(world) -> None:
    st, goal = world.scenarios.starts[0], world.scenarios.targets[0].position
    planner = make_planner(max_iterations=1)
    with pytest.raises(NoPathError, match=r'^rrt found no path within max_iterations 1 '
                                          r'\(1 iterations, 2 nodes, seed 0\)$') as info:
        planner.plan(st.position, st.rotation, goal)
    assert '\n' not in str(info.value)
    assert (info.value.reason, info.value.step) == ('max_iterations', 1)


def test_start_without_clearance_is_refused(world, planner) -> None:
    st, goal = world.scenarios.starts[0], world.scenarios.targets[0].position
    # 11 mm sideways from the centerline start: beyond the wall or against it
    off = st.position + 0.011 * st.rotation[:, 0]
    with pytest.raises(InvalidInputError, match=r'rrt start: expected the tip at least 4\.25 mm '
                                                r'from the wall inside the lumen, found'):
        planner.plan(off, st.rotation, goal)


def test_bend_radius_comes_from_the_catheter_model(world) -> None:
    cat = CatheterConfig(theta_max=math.radians(120.0), segment_length=0.04)
    config = PlannerConfig(planner_type='rrt', catheter=cat)
    planner = Planner(config, model_world_from_sim(world), StaticWall(world.anatomy), None)
    assert planner.rrt is not None
    assert planner.rrt.r_min == pytest.approx(0.04 / math.radians(120.0))
    assert planner.rrt.required == pytest.approx(cat.radius + 0.0005 + 0.00025)


@pytest.mark.parametrize(('field', 'value', 'match'), [
    ('time_limit_s', 0.0, r'time_limit_s must be in \(0.0, 60.0\], found 0.0'),
    ('time_limit_s', math.nan, 'time_limit_s must be in'),
    ('max_iterations', 0, r'max_iterations must be an int in \[1, 1000000\], found 0'),
    ('max_iterations', 1.5, 'max_iterations must be an int'),
    ('max_iterations', True, 'max_iterations must be an int'),
    ('seed', -1, r'seed must be an int in \[0, 2147483647\], found -1'),
    ('seed', 1.5, 'seed must be an int'),
    ('clearance_margin', 0.01, r'clearance_margin must be in \[0.0, 0.005\], found 0.01'),
    ('range', 0.001, r'range must be in \[0.002, 0.2\], found 0.001'),
    ('resolution', 0.0, r'resolution must be in \[0.0001, 0.002\], found 0.0'),
])
def test_bad_settings_raise_one_line(field, value, match) -> None:
    with pytest.raises(ValueError, match=match) as info:
        replace(RrtConfig(), **{field: value})
    assert '\n' not in str(info.value)
    with pytest.raises(ValueError, match='rrt must be an RrtConfig'):
        PlannerConfig(planner_type='rrt', rrt={'seed': 1})  # type: ignore[arg-type]


#: Measured (the default budget of 1000 iterations, 60 s limit, bench/bench_planner_rrt.py,
#: seed 0): default 15/15 with numpy's AVX-512, AVX2 and baseline (SSE) kernels; elongated 14/15
#: (AVX-512), 11/15 (AVX2, ``NPY_DISABLE_CPU_FEATURES=X86_V4``), 14/15 (baseline). The budget
#: makes the count independent of the load, not of the CPU: numpy's SIMD kernels change the last
#: bits of the anatomy built from its parameters, and the search amplifies them. The bar is
#: below every count measured.
MIN_SUCCESS = {'default': 14, 'elongated': 10}


@pytest.mark.slow
@pytest.mark.parametrize('anatomy', ['default', 'elongated'])
def test_success_over_the_15_start_target_pairs(anatomy) -> None:
    planner = make_planner(anatomy)
    sc = load_world(anatomy).scenarios
    ok = 0
    for st in sc.starts:
        for tg in sc.targets:
            try:
                result = planner.plan(st.position, st.rotation, tg.position)
            except NoPathError:
                continue
            assert planner.rrt is not None
            r_min = planner.rrt.r_min
            assert discrete_curvature(result.raw).max() <= CURVATURE_ALLOWANCE / r_min
            assert discrete_curvature(result.path).max() <= PATH_CURVATURE_ALLOWANCE / r_min
            ok += 1
    assert ok >= MIN_SUCCESS[anatomy], f'{anatomy}: {ok}/15 planned'
