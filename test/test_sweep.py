"""bench/sweep.py: its configuration, the shared-folder probe, study tasks on local Ray (bound to
127.0.0.1), and real tiny sweeps with their re-runs."""

from __future__ import annotations

import os
from pathlib import Path
import subprocess
import sys
import time

from bench_modules import bench_module
import pytest

WS = Path(__file__).resolve().parent.parent
study = bench_module('insilico_study')
sweep = bench_module('sweep')

TINY = """presets: [smoke]
seeds: {seeds}
anatomies: {anatomies}
budgets: [1024]
modes: [static]
trials: 2
baselines: []
"""


# ---------------------------------------------------------------------------- configuration


def test_the_shipped_configurations_load():
    full = sweep.load_sweep(WS / 'bench' / 'sweeps' / 'full_study.yaml')
    assert full.methods == ('cgail', 'gail', 'mu0', 'lambda0', 'nu0') and len(full.seeds) >= 3
    assert [a.name for a in full.anatomies] == ['default', 'elongated']
    assert full.budgets == (500_000, 2_000_000) and full.modes == ('static', 'dynamic')
    assert len(study.plan_tasks(study.Layout(Path('/nowhere')), full)) == 808
    smoke = sweep.load_sweep(WS / 'bench' / 'sweeps' / 'smoke.yaml')
    assert (smoke.methods, smoke.seeds, smoke.budgets, smoke.trials) == (
        ('smoke',), (0, 1), (1024,), 2)
    assert [a.demos for a in smoke.anatomies] == [(WS / 'bags' / 'demos' / 'default',),
                                                 (WS / 'bags' / 'demos' / 'elongated',)]
    # the study at the authors' budgets: the same plan as its insilico_study command line
    authors = sweep.load_sweep(WS / 'bench' / 'sweeps' / 'authors.yaml')
    args = study.build_parser().parse_args([
        '--methods', 'paper_code_cgail', 'paper_code_gail', 'cgail', 'gail', 'mu0', 'lambda0',
        'nu0', '--seeds', '0', '1', '2', '--authors-budgets', '--fresh-budgets', '--modes',
        'static', 'dynamic'])
    cli = study.check_args(args)
    assert authors.fresh and authors.method_budgets == cli.method_budgets == {
        'paper_code_cgail': (8_000_000,), 'paper_code_gail': (1_275_443, 5_000_000),
        'cgail': (500_000,), 'gail': (2_000_000,), 'mu0': (500_000,), 'lambda0': (500_000,),
        'nu0': (500_000,)}
    layout = study.Layout(Path('/nowhere'), fresh=True)
    keys = [t.key for t in study.plan_tasks(layout, authors)]
    assert keys == [t.key for t in study.plan_tasks(layout, cli)] and len(keys) == 200


def test_an_anatomy_mapping_says_what_train_and_evaluate_are_told():
    plan = sweep._plan({'presets': ['smoke'], 'seeds': [0], 'budgets': [1024], 'anatomies': [
        {'name': 'population', 'train': [], 'evaluate': ['--population', 20],
         'demos': ['bags/demos/default']}]})
    assert plan.anatomies == (study.Anatomy('population', (), ('--population', '20'),
                                            (WS / 'bags' / 'demos' / 'default',)),)
    tasks = {t.key: t for t in study.plan_tasks(study.Layout(Path('/out')), plan)}
    cmd = tasks['population/smoke/seed0/1024/eval-static-targets1'].command()
    assert cmd[cmd.index('--population') + 1] == '20' and '--anatomy' not in cmd
    assert tasks['population/smoke/seed0/1024/train-static'].run == Path(
        '/out/anatomies/population/smoke/seed0/static')


GOOD = {'presets': ['smoke'], 'seeds': [0], 'budgets': [1024], 'anatomies': ['default']}


@pytest.mark.parametrize('change, message', [
    ({'seed': [0]}, "expected keys ['presets', 'seeds', 'anatomies', 'budgets'] and optional "
                    "['modes', 'trials', 'dynamic_steps', 'unseen_scenario_seed', 'baselines', "
                    "'authors_budgets', 'fresh_budgets'], found unknown ['seed']"),
    ({'presets': None}, 'presets: expected a non-empty list of strings, found None'),
    ({'presets': ['nope']}, 'presets: expected a preset name in ['),
    ({'seeds': [0, 'one']}, "seeds: expected a non-empty list of integers, found [0, 'one']"),
    ({'seeds': [0, 0]}, 'seeds: expected distinct values, found [0, 0]'),
    ({'budgets': [2048, 1024]}, 'budgets: expected strictly increasing budgets'),
    ({'anatomies': []}, 'anatomies: expected a non-empty list, found []'),
    ({'anatomies': ['no/such/aorta']}, "anatomies[0]: anatomy: expected a built-in anatomy"),
    ({'anatomies': ['default', 'default']},
     "anatomies: expected distinct names, found ['default', 'default']"),
    ({'anatomies': [{'name': 'x y'}]}, "anatomies[0]: expected a name of letters"),
    ({'anatomies': [{'name': 'p', 'eval': []}]}, "anatomies[0]: expected a mapping with keys"),
    ({'anatomies': [{'name': 'p', 'demos': ['bags/none']}]},
     'anatomies[0]: expected existing demonstrations, found none at'),
    ({'modes': ['beating']}, "modes: expected some of ['static', 'dynamic'], found ['beating']"),
    ({'trials': 0}, 'trials: expected >= 1, found 0'),
    ({'trials': 'many'}, "trials: expected an integer, found 'many'"),
    ({'baselines': ['rrt']}, "baselines: expected some of ['centerline', 'expert']"),
    ({'unseen_scenario_seed': 0}, 'unseen_scenario_seed: expected a target set other than'),
    ({'authors_budgets': 'yes'}, "authors_budgets: expected true or false, found 'yes'"),
    ({'authors_budgets': True}, 'budgets: expected no budgets with --authors-budgets'),
])
def test_bad_configuration_is_one_line_and_exit_2(change, message, tmp_path, capsys):
    import yaml

    config = tmp_path / 'bad.yaml'
    config.write_text(yaml.safe_dump({**GOOD, **change}))
    assert sweep.main([str(config), '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'sweep: error: {config}: {message}'), err
    assert err.count('\n') == 1
    assert not (tmp_path / 'out').exists()


@pytest.mark.parametrize('argv, message', [
    (['--num-cpus', '0'], '--num-cpus: expected >= 1, found 0'),
    (['--address', '10.0.0.1:6379', '--no-ray'], '--address: expected neither --num-cpus nor'),
])
def test_bad_options_are_one_line(argv, message, tmp_path, capsys):
    config = WS / 'bench' / 'sweeps' / 'smoke.yaml'
    assert sweep.main([str(config), *argv, '--out', str(tmp_path / 'out')]) == 2
    err = capsys.readouterr().err
    assert err == f'sweep: error: {message}' + err.split(message, 1)[1]
    assert err.count('\n') == 1 and not (tmp_path / 'out').exists()


def test_an_unreadable_configuration_is_one_line(tmp_path, capsys):
    assert sweep.main([str(tmp_path / 'none.yaml')]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f'sweep: error: {tmp_path / "none.yaml"}: expected a readable YAML '
                          'file, found FileNotFoundError') and err.count('\n') == 1


# ---------------------------------------------------------------------------- shared folder


def test_a_node_reports_what_it_cannot_see(tmp_path):
    probe = tmp_path / 'probe'
    assert sweep.node_sees(str(probe), 'tok', sys.executable).startswith(
        f'cannot read {probe} (No such file or directory)')
    probe.write_text('other')
    assert sweep.node_sees(str(probe), 'tok', sys.executable) == (
        f'reads another {probe} (not the same filesystem)')
    probe.write_text('tok')
    assert sweep.node_sees(str(probe), 'tok', '/no/python') == (
        'has no interpreter /no/python (the workspace is not at the same path)')
    assert sweep.node_sees(str(probe), 'tok', sys.executable) == ''
    assert sorted(p.name for p in tmp_path.iterdir()) == ['probe']  # its reply is gone


# ---------------------------------------------------------------------------- Ray


def _listening(pids: set[int]) -> list[str]:
    """Local addresses of the TCP sockets that ``pids`` or Ray's servers listen on."""
    out = subprocess.run(['ss', '-ltnpH'], capture_output=True, text=True, check=True).stdout
    found = []
    for line in out.splitlines():
        users = line.split('users:', 1)[-1]
        if any(f'pid={p},' in users for p in pids) or any(
                name in users for name in ('"gcs_server"', '"raylet"', '"ray::')):
            found.append(line.split()[3])
    return found


def test_study_tasks_on_local_ray(tmp_path, capsys):
    """The study's scheduler with Ray tasks: dependencies, a failure that blocks its
    dependants, a second run that skips what is done, a cancelled task whose process stops;
    every Ray server listens on 127.0.0.1 only."""
    layout = study.Layout(tmp_path)

    def touch(key: str, deps: list[str], code: str = '') -> object:
        marker = tmp_path / f'{key}.done'
        script = code or f'open({str(marker)!r}, "w").write("x")'
        return study.Task(key, 'eval', deps, done=marker.is_file,
                          command=lambda: [sys.executable, '-c', script])

    tasks = [touch('b', ['a']), touch('a', []),
             touch('bad', [], code='import sys; print("boom"); sys.exit(3)'),
             touch('after-bad', ['bad'])]
    with sweep.ray_launcher(tmp_path, None, 2) as (launch, cpus):
        assert cpus == 2
        addresses = _listening({os.getpid()})
        assert addresses and all(a.startswith(('127.0.0.1:', '[::ffff:127.0.0.1]:', '[::1]:'))
                                 for a in addresses), addresses
        assert study.run_tasks(tasks, layout, cpus, 3600.0, launch=launch) == (2, 2)
        out = capsys.readouterr().out
        assert ' FAILED bad: exit 3 after ' in out and out.count('FAILED') == 1
        assert (tmp_path / 'b.done').is_file() and not (tmp_path / 'after-bad.done').exists()
        assert 'boom' in (tmp_path / 'logs' / 'bad.log').read_text()
        assert study.run_tasks(tasks[:2], layout, cpus, 3600.0, launch=launch) == (2, 0)
        assert '2 tasks: 2 already done, 0 to run' in capsys.readouterr().out

        # A task's process runs at the driver's priority, not Ray's worker niceness (15).
        nice = launch([sys.executable, '-c', 'import os; print("niceness", os.nice(0))'],
                      tmp_path / 'nice.log')
        assert nice.wait(timeout=120) == 0
        assert f'niceness {os.nice(0)}' in (tmp_path / 'nice.log').read_text()
        assert 'sweep: this task runs at niceness' not in (tmp_path / 'nice.log').read_text()

        pid_file = tmp_path / 'pid'
        proc = launch([sys.executable, '-c', f'import os, time; open({str(pid_file)!r}, "w")'
                       '.write(str(os.getpid())); time.sleep(600)'], tmp_path / 'sleep.log')
        deadline = time.monotonic() + 60
        while not pid_file.is_file() or not pid_file.read_text():
            assert time.monotonic() < deadline and proc.poll() is None
            time.sleep(0.1)
        pid = int(pid_file.read_text())
        proc.terminate()
        assert proc.wait(timeout=60) == -15
        deadline = time.monotonic() + 30
        while Path(f'/proc/{pid}').exists() and 'State:\tZ' not in Path(
                f'/proc/{pid}/status').read_text():
            assert time.monotonic() < deadline, 'the cancelled task left its process running'
            time.sleep(0.1)


def _sweep(config: Path, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(WS / 'bench' / 'sweep.py'), str(config),
                           '--out', str(out), '--num-cpus', '2', '--progress-every', '3600',
                           *extra], capture_output=True, text=True, timeout=900, cwd=WS)


def _check_tiny(out: Path, seeds: list[int], anatomies: list[str], stdout: str) -> None:
    n = len(seeds) * len(anatomies) * 4  # train, export, 2 evaluations
    assert f'{n} tasks: 0 already done, {n} to run, 2 at a time' in stdout, stdout
    assert f'{n} of {n} tasks done' in stdout
    rows = (out / 'results.csv').read_text().splitlines()
    assert rows[0] == 'anatomy,options,preset,seed,budget,steps,mode,targets,successes,trials'
    got = sorted((r.split(',')[0], r.split(',')[3], r.split(',')[7]) for r in rows[1:])
    assert got == sorted((a, str(s), t) for a in anatomies for s in seeds
                         for t in ('training', 'unseen (scenario seed 1)'))
    assert all(r.endswith(',2') and r.split(',')[5] == '1024' for r in rows[1:])
    report = (out / 'report.md').read_text()
    head = '| anatomy | method |' if len(anatomies) > 1 else '| method |'
    assert head + ' steps used (authors\') | static: paper |' in report
    for a in anatomies:
        assert (f'| `{a}` | smoke (`smoke`) | 1,024 (authors: -) | - |' in report
                if len(anatomies) > 1 else '| smoke (`smoke`) | 1,024 (authors: -) | - |'
                in report)


def test_a_tiny_sweep_on_local_ray_and_its_rerun(tmp_path):
    """The CI sweep (the fast variant of the one below, whose budgets continue one run):
    smoke, one seed, in the elongated anatomy (its own folder), each budget a run of its own
    (``fresh_budgets``, as the authors' study), on local Ray with 2 CPUs; a second run runs
    nothing."""
    config = tmp_path / 'tiny.yaml'
    config.write_text(TINY.format(seeds='[0]', anatomies='[elongated]')
                      + 'fresh_budgets: true\n')
    out = tmp_path / 'out'
    first = _sweep(config, out)
    assert first.returncode == 0, first.stdout[-2000:] + first.stderr[-2000:]
    _check_tiny(out, [0], ['elongated'], first.stdout)
    run = out / 'anatomies' / 'elongated' / 'smoke' / 'seed0' / 'budget_1024'
    assert (run / 'static.onnx').is_file() and (run / 'static' / 'scalars.csv').is_file()
    again = _sweep(config, out)
    assert again.returncode == 0, again.stdout[-2000:] + again.stderr[-2000:]
    assert '4 tasks: 4 already done, 0 to run' in again.stdout
    assert 'every task is done: no Ray needed' in again.stdout and 'Ray up' not in again.stdout
    assert 'start ' not in again.stdout


@pytest.mark.slow
def test_the_smoke_sweep_2_seeds_x_2_anatomies(tmp_path):
    """bench/sweeps/smoke.yaml as shipped: 2 seeds x 2 anatomies on local Ray with 2 CPUs
    (about 3 min on 2 cores)."""
    out = tmp_path / 'out'
    run = _sweep(WS / 'bench' / 'sweeps' / 'smoke.yaml', out)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    _check_tiny(out, [0, 1], ['default', 'elongated'], run.stdout)
    assert (out / 'curves_elongated_ours_static.png').is_file()
    again = _sweep(WS / 'bench' / 'sweeps' / 'smoke.yaml', out)
    assert again.returncode == 0 and '16 tasks: 16 already done, 0 to run' in again.stdout
