"""An anatomy is a name or a path: the one resolver, its labels, its cache and its errors, and
the simulator (EnvConfig, gym.make, load_world) taking any of them (issue 12)."""

from __future__ import annotations

import dataclasses
import os

import gymnasium as gym
import numpy as np
import pytest

import cgail_sim  # noqa: F401  (registers the gymnasium ids)
from cgail_sim.anatomy import (
    Anatomy,
    AnatomyError,
    build_anatomy,
    MeshLoadError,
    save_anatomy_mesh,
)
from cgail_sim.anatomy_spec import (
    anatomy_identity,
    anatomy_label,
    check_anatomy_spec,
    is_builtin,
    is_named,
    real_anatomy_dir,
    REAL_HELD_OUT,
    REAL_NAMES,
    resolve_anatomy,
)
from cgail_sim.config import EnvConfig
from cgail_sim.env import CatheterNavEnv
from cgail_sim.testing import curved_anatomy
from cgail_sim.wall import DeformableWall
from cgail_sim.worlds import load_world

USAGE = (r"expected a built-in anatomy name \['default', 'elongated'\], a population sample "
         r"population-<seed>, a real aorta avt-<case> \(avt-D2, [^)]*\), "
         r"a prepared anatomy directory \(holding lumen.stl and lumen.yaml\) "
         r"or a mesh file \(.stl/.obj/.ply in mm, with its <stem>.yaml landmarks\), found ")


PREPARED_FROM = 'elongated'  # (the prepared fixture's aorta, cgail_sim.testing)


def test_a_name_is_the_cached_built_in_anatomy() -> None:
    assert resolve_anatomy('default') is build_anatomy('default')
    assert is_builtin('elongated') and not is_builtin('./elongated')
    assert anatomy_label('elongated') == 'elongated'


def test_a_population_name_is_that_sample_everywhere() -> None:
    from cgail_sim.anatomy_spec import anatomy_identity, anatomy_label, check_anatomy_spec
    from cgail_sim.population import sample_anatomy

    a = resolve_anatomy('population-10003')
    assert a is sample_anatomy(10003) and a.name == 'population-10003'
    assert anatomy_label('population-10003') == 'population-10003'
    assert anatomy_identity('population-10003') == ('population-10003', a.content_hash)
    check_anatomy_spec('population-10003')
    for bad in ('population-', 'population-x1', 'population--3'):
        with pytest.raises(AnatomyError, match=USAGE):
            check_anatomy_spec(bad)


def test_a_prepared_directory_and_its_mesh_resolve_to_one_cached_anatomy(prepared) -> None:
    a = resolve_anatomy(prepared)
    assert isinstance(a, Anatomy) and a.name == 'p07'
    assert resolve_anatomy(str(prepared)) is a
    assert resolve_anatomy(prepared / 'lumen.stl') is a
    assert resolve_anatomy(prepared / '..' / 'p07') is a
    assert anatomy_label(prepared) == anatomy_label(prepared / 'lumen.stl') == 'p07'
    assert resolve_anatomy(a) is a
    # the same mesh as the built-in it was written from, up to the mm rounding of the file
    e = build_anatomy('elongated')
    assert len(a.vertices) == len(e.vertices) and a.content_hash != e.content_hash
    assert np.abs(np.sort(a.vertices, axis=0) - np.sort(e.vertices, axis=0)).max() < 1e-6


def test_an_edited_file_is_read_again(prepared, tmp_path) -> None:
    d = tmp_path / 'p08'
    d.mkdir()
    for f in ('lumen.stl', 'lumen.yaml'):
        (d / f).write_bytes((prepared / f).read_bytes())
    first = resolve_anatomy(d)
    assert first.name == 'p08' and first.content_hash == resolve_anatomy(prepared).content_hash
    stat = (d / 'lumen.yaml').stat()
    os.utime(d / 'lumen.yaml', ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000_000))
    again = resolve_anatomy(d)
    assert again is not first and again.content_hash == first.content_hash


def test_a_mesh_file_with_its_sidecar_is_labelled_by_its_stem(tmp_path) -> None:
    save_anatomy_mesh(build_anatomy('default'), tmp_path / 'aorta 1.stl')
    a = resolve_anatomy(tmp_path / 'aorta 1.stl')
    assert a.name == anatomy_label(tmp_path / 'aorta 1.stl') == 'aorta_1'


@pytest.mark.parametrize(('make', 'match'), [
    (lambda d: 'no_such_anatomy', USAGE + r"'no_such_anatomy': no such file or directory$"),
    (lambda d: d / 'missing', USAGE + r"'.*/missing': no such file or directory$"),
    (lambda d: d, r"^anatomy .*/bad: expected a prepared anatomy directory holding lumen.stl "
                  r"and lumen.yaml \(cgail prepare-anatomy makes one\), found no lumen.yaml$"),
    (lambda d: d / 'notes.txt', r"^anatomy .*/notes.txt: expected a mesh file \(.stl/.obj/.ply\) "
                                r"or a prepared anatomy directory, found a .txt file$"),
    (lambda d: d / 'bare.stl', r"^anatomy .*/bare.stl: expected its landmarks in "
                               r".*/bare.yaml, found no such file$"),
    (lambda d: d / 'refused', r"^anatomy .*/refused: expected a usable prepared anatomy "
                              r"\(lumen.stl\), found one cgail prepare-anatomy refused "
                              r"\(lumen.rejected.stl; the reasons are in .*/refused/report.md\)$"),
    (lambda d: '', USAGE + "''$"),
    (lambda d: 3, USAGE + 'an object of type int$'),
])
def test_bad_anatomy_arguments_say_what_was_wrong_in_one_line(tmp_path, make, match) -> None:
    d = tmp_path / 'bad'
    d.mkdir()
    (d / 'lumen.stl').write_text('solid x\nendsolid x\n')
    (d / 'notes.txt').write_text('not a mesh')
    (d / 'bare.stl').write_text('solid x\nendsolid x\n')
    (d / 'refused').mkdir()
    for name in ('lumen.rejected.stl', 'lumen.rejected.yaml', 'report.md'):
        (d / 'refused' / name).write_text('x\n')
    spec = make(d)
    for call in (resolve_anatomy, check_anatomy_spec, lambda s: EnvConfig(anatomy=s)):
        with pytest.raises(AnatomyError, match=match) as info:
            call(spec)
        assert '\n' not in str(info.value)


def test_a_mesh_that_fails_to_load_names_the_file(tmp_path) -> None:
    d = tmp_path / 'junk'
    d.mkdir()
    (d / 'lumen.stl').write_text('solid junk\nthis is not a facet\nendsolid junk\n')
    (d / 'lumen.yaml').write_text('units: mm\n')
    check_anatomy_spec(d)  # (the files are there: the config accepts it)
    with pytest.raises(MeshLoadError, match=r"^expected a triangle mesh in .*/junk/lumen.stl, "
                                            r"found a Trimesh with 0 faces$"):
        resolve_anatomy(d)
    with pytest.raises(MeshLoadError, match=r"junk/lumen.stl"):
        CatheterNavEnv(EnvConfig(anatomy=d))


def test_an_anatomy_shows_as_one_short_line() -> None:
    a = build_anatomy('default')
    assert repr(a) == (f"Anatomy(name='default', {len(a.vertices)} vertices, {len(a.faces)} "
                       f"faces, content_hash='{a.content_hash}')")
    with pytest.raises(ValueError, match=r'^max_steps must be an int in \[1, 1000000\], found 0$'):
        EnvConfig(anatomy=a, max_steps=0)
    assert len(repr(EnvConfig(anatomy=a))) < 1000


@pytest.mark.parametrize('make', [
    lambda a: EnvConfig(anatomy=a, mode='beating'),
    lambda a: EnvConfig(anatomy=a, theta_max=9.0),
    lambda a: EnvConfig(anatomy=a, reward=None),
    lambda a: EnvConfig(anatomy=a.vertices),
    lambda a: EnvConfig(anatomy={'vertices': a.vertices}),
    lambda a: gym.make('CatheterNav-v0', anatomy=a, max_steps=0),
    lambda a: gym.make('CatheterNav-v0', anatomy=a.vertices),
], ids=['mode', 'theta_max', 'reward', 'vertex array', 'dict of arrays', 'gym.make kwargs',
        'gym.make array'])
def test_errors_around_an_anatomy_never_print_its_arrays(make) -> None:
    """An error that involves an Anatomy (or arrays passed as one) is one short line: no
    vertex coordinates, whatever the field."""
    a = build_anatomy('default')
    with pytest.raises((ValueError, TypeError)) as info:
        make(a)
    text = str(info.value)
    assert '\n' not in text and len(text) < 400, text
    assert 'array(' not in text and '[[' not in text, text  # (numpy prints rows as [[...


def test_the_simulator_takes_a_path_everywhere(prepared) -> None:
    # (worlds are cached by content: another test's copy of this mesh may have built it first)
    anatomy = resolve_anatomy(prepared)
    same = (anatomy.name, anatomy.content_hash)
    world = load_world(prepared)
    assert (world.anatomy.name, world.anatomy.content_hash) == same
    assert load_world(str(prepared)) is world and load_world(anatomy) is world
    env = CatheterNavEnv(EnvConfig(anatomy=prepared))
    assert env.anatomy is world.anatomy
    for make in (lambda: gym.make('CatheterNav-v0', anatomy=str(prepared)),
                 lambda: gym.make('CatheterNavDynamic-v0', anatomy=prepared)):
        made = make().unwrapped
        assert made.anatomy is world.anatomy
        obs, _ = made.reset(seed=0, options={'start': 0, 'target': 0})
        assert obs.shape == (41,) and np.isfinite(obs).all()
        made.step(np.array([0.0, 0.0, 1.0], dtype=np.float32))
    assert gym.make('CatheterNavDynamic-v0', anatomy=prepared).unwrapped.config.mode == 'dynamic'


def test_the_curved_aorta_runs_in_the_beating_wall_within_its_bound() -> None:
    """Issue 12's case end to end, with no monkeypatch: the dynamic env from every start of
    the curved descending aorta, 30 steps of full insertion, never leaves the wall's bound."""
    env = CatheterNavEnv(EnvConfig(mode='dynamic', anatomy=curved_anatomy()))
    assert [s.bent for s in env.scenarios.starts] == [False, True, True]
    for start in range(3):
        env.reset(seed=0, options={'start': start, 'target': 0})
        wall = env.engine.walls[0]
        assert isinstance(wall, DeformableWall)
        worst = 0.0
        for _ in range(30):
            info = env.step(np.array([0.0, 0.0, 1.0], dtype=np.float32))[4]
            worst = max(worst, wall.max_displacement)
            assert not info['collision']
        assert 0.005 < worst <= wall.pbd_config.max_displacement


def test_retracting_from_a_bent_introducer_exits_without_a_collision() -> None:
    env = CatheterNavEnv(EnvConfig(anatomy=curved_anatomy()))
    env.reset(seed=0, options={'start': 2, 'target': 0})
    steps = 0
    while True:
        _, reward, terminated, _, info = env.step(np.array([0.0, 0.0, -1.0], dtype=np.float32))
        steps += 1
        if terminated or steps == 400:
            break
    assert info['exited'] and not info['collision'] and reward < 0
    assert steps * 0.0005 > 0.07  # it slid back along the whole introducer


def test_a_config_keeps_the_anatomy_it_was_given(prepared) -> None:
    cfg = EnvConfig(anatomy=prepared)
    assert cfg.anatomy == prepared
    assert dataclasses.replace(cfg, mode='dynamic').anatomy == prepared


def test_real_aortas_are_named_anatomies() -> None:
    """``avt-<case>``: the shipped prepared AVT cases, by name, like a built-in one; their
    identity is the mesh's content hash (a policy contract names it), and the held-out ones are
    among them."""
    assert tuple(f'avt-D{n}' for n in (2, 4, 8, 10, 11, 13, 14, 15, 16, 18)) == REAL_NAMES
    assert set(REAL_HELD_OUT) < set(REAL_NAMES)
    assert REAL_NAMES[1::2] == REAL_HELD_OUT  # the rule: every other case, from the second
    for name in ('avt-D18', 'avt-D2'):
        assert is_named(name) and not is_builtin(name)
        check_anatomy_spec(name)
        anatomy = resolve_anatomy(name)
        assert anatomy.name == anatomy_label(name) == name
        assert anatomy is resolve_anatomy(name)  # (loaded once)
        label, digest = anatomy_identity(name)
        assert label == name and len(digest) == 16
        # the same anatomy as its prepared directory
        assert resolve_anatomy(real_anatomy_dir(name)).content_hash == digest
    assert real_anatomy_dir('avt-D3') is None and not is_named('avt-D3')
    with pytest.raises(AnatomyError, match=USAGE + r"'avt-D3': no such file or directory"):
        resolve_anatomy('avt-D3')


def test_a_real_aorta_runs_in_the_simulator_by_name() -> None:
    env = CatheterNavEnv(EnvConfig(mode='static', anatomy='avt-D18'))
    obs, _ = env.reset(seed=0)
    assert np.all(np.isfinite(obs))
    assert env.unwrapped.engine.world.anatomy.name == 'avt-D18'
