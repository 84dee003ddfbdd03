"""Sweeps on Ray: the in-silico study over presets x seeds x anatomies, as Ray tasks.

Run (from the workspace root, inside the workspace environment)::

    scripts/ws python bench/sweep.py bench/sweeps/smoke.yaml          # local Ray, minutes
    scripts/ws python bench/sweep.py bench/sweeps/full_study.yaml \\
        --address HEAD_IP:6379 --out /shared/runs/full_study         # the full study, a cluster
    scripts/ws python bench/sweep.py bench/sweeps/full_study.yaml --report-only

The sweep is ``bench/insilico_study.py`` (its tasks, layout, resuming and report) with two
things added: an anatomy axis, and Ray as the executor. From the configuration (a YAML file,
below) it plans the study's tasks for every preset, seed, budget, mode and anatomy: static
training, dynamic re-training, export, evaluation on the training and on unseen targets, and the
baselines. Each task is one Ray task (``num_cpus=1``) that runs the study's command line as one
child process with one torch thread (the study's ``child_env``), its output appended to
``OUT/logs/<task>.log``. The driver (this process) keeps the study's scheduler: it submits a
task when its dependencies are done, at most as many at a time as the cluster has CPUs, takes
the snapshots between budgets, and rewrites ``OUT/report.md`` (one table per option set and
budget, a row per anatomy and preset; learning curves per anatomy) and ``OUT/results.csv`` after
every evaluation and at the end.

**Resuming.** Re-running the same command skips what is done and continues unfinished
trainings from their checkpoints, as the study does. Ctrl-C or SIGTERM cancels the running Ray
tasks; each stops its process (SIGTERM, then SIGKILL after 30 s) and the checkpoints stay.

**Local Ray** (the default): ``ray.init(address='local', num_cpus=--num-cpus)``, every server
bound to 127.0.0.1, no dashboard; nothing listens beyond this machine. Its workers run at
niceness 0 (``RAY_worker_niceness=0``, as Ray's own job manager sets): Ray's default, 15, is
inherited by every task's process, which then gets a few per cent of a CPU beside any other
work on the machine (a 20 s training took 6.6 min beside a busy loop on each core).

**Nothing to run.** When every task of the plan is done, the sweep starts no Ray at all: it
says so and rewrites the report (seconds, not Ray's start-up).

**A cluster** (``--address HOST:PORT``): start a head and workers from the workspace environment
of every node, e.g. ``scripts/ws ray start --head --port 6379 --num-cpus 16`` on the head and
``scripts/ws ray start --address HEAD_IP:6379`` on each worker, all of them and the sweep with
``RAY_AUTH_MODE=token`` and the same token (``ray get-auth-token --generate``;
docs/tutorials/train.md has the commands), and with ``RAY_worker_niceness=0`` where the nodes
run other work too (a task's
log says when it runs at a niceness above the sweep's). The sweep assumes a **shared
filesystem**: every node sees the workspace (the same interpreter path) and ``--out`` at the
same path as the driver, since the tasks write their runs there and the driver reads them back.
It checks that at start: a probe on every node reads a file the driver wrote in ``--out`` and
writes one beside it; a node that cannot ends the sweep with a one-line error before anything
runs. Numbers of a node with other SIMD instructions may differ in the last bits (``docs``:
``NPY_DISABLE_CPU_FEATURES``); set such variables in the driver's environment, which every task
inherits.

Configuration (YAML; relative paths are relative to the workspace root)::

    presets: [cgail, gail]          # training presets (config/presets/), >= 1
    seeds: [0, 1, 2]                # training seeds, >= 1
    anatomies: [default, elongated] # see below, >= 1
    budgets: [500000, 2000000]      # static step budgets, increasing (a larger one continues)
    authors_budgets: false          # optional: true for each preset's own budgets instead
                                    # (the study's --authors-budgets; then no budgets key)
    fresh_budgets: false            # optional: true to train each budget from scratch
    modes: [static, dynamic]        # optional (default both)
    trials: 100                     # optional: evaluation trials per policy and target set
    dynamic_steps: 102400           # optional: dynamic re-training from each static best
    unseen_scenario_seed: 1         # optional: the unseen target set
    baselines: [centerline]         # optional: reference methods ([] for none)

An anatomy is a built-in name or a prepared anatomy path (``train``/``evaluate --anatomy X``,
demonstrations ``bags/demos/<name>``, for a path ``bags/demos/default`` re-simulated), or a
mapping that says what ``train`` and ``evaluate`` are told, for anatomies drawn another way::

    - {name: population, train: [], evaluate: [--population, '20'],
       demos: [bags/demos/population]}
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator
import contextlib
import dataclasses
import os
from pathlib import Path
import re
import shlex
import subprocess
import sys
import time
from typing import Any
import uuid

import insilico_study as study
import yaml

WS = study.WS
REQUIRED = ('presets', 'seeds', 'anatomies', 'budgets')
OPTIONAL: dict[str, Any] = {'modes': list(study.MODES), 'trials': 100,
                            'dynamic_steps': 102_400, 'unseen_scenario_seed': 1,
                            'baselines': ['centerline'], 'authors_budgets': False,
                            'fresh_budgets': False}
#: The switches among OPTIONAL (the study's flags of the same names); ``authors_budgets: true``
#: replaces ``budgets`` (each preset gets its own, as ``--authors-budgets`` gives them).
SWITCHES = ('authors_budgets', 'fresh_budgets')
#: The study's flag of each configuration key (its errors name the flag; ours the key).
STUDY_FLAG = {'presets': 'methods', 'seeds': 'seeds', 'budgets': 'steps', 'modes': 'modes',
              'trials': 'trials', 'dynamic_steps': 'dynamic_steps',
              'unseen_scenario_seed': 'unseen_scenario_seed', 'baselines': 'baselines',
              'authors_budgets': 'authors_budgets', 'fresh_budgets': 'fresh_budgets'}
BASELINES = ('centerline', 'expert')
ANATOMY_KEYS = ('name', 'train', 'evaluate', 'demos')
NAME = re.compile(r'[A-Za-z0-9][A-Za-z0-9_.-]*')
#: Set before ray is imported and started: ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` makes a local
#: Ray bind every server to 127.0.0.1 (Ray reads it at import; on Linux its default, 1, binds
#: them to all interfaces); ``RAY_worker_niceness=0`` runs its workers, and so every task's
#: process, at the driver's priority (the raylet reads it at start; default 15).
LOCAL_RAY = {'RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER': '0', 'RAY_worker_niceness': '0'}


class SweepError(study.StudyError):
    """A one-line failure of the sweep (bad configuration, a node without the run folder)."""


# ------------------------------------------------------------------------------------------
# Configuration.


def _ints(key: str, value: Any) -> list[int]:
    if not isinstance(value, list) or not value or not all(
            isinstance(v, int) and not isinstance(v, bool) for v in value):
        raise SweepError(f'{key}: expected a non-empty list of integers, found {value!r}')
    return value


def _strings(key: str, value: Any, empty: bool = False) -> list[str]:
    if (not isinstance(value, list) or (not value and not empty)
            or not all(isinstance(v, (str, int)) and not isinstance(v, bool) for v in value)):
        raise SweepError(f'{key}: expected a {"" if empty else "non-empty "}list of strings, '
                         f'found {value!r}')
    return [str(v) for v in value]


def _path(value: str) -> Path:
    path = Path(value).expanduser()
    return path if path.is_absolute() else WS / path


def parse_anatomy(item: Any, where: str) -> study.Anatomy:
    """One entry of ``anatomies``: a name or path, or a mapping (module docstring).

    Raises:
        SweepError: an unknown key, a bad name, argument list or missing demonstrations.
    """
    if isinstance(item, str):
        from cgail_sim.anatomy_spec import is_builtin

        spec = item if is_builtin(item) else str(_path(item))
        try:
            anatomy = study.Anatomy.named(spec)
        except study.StudyError as exc:
            raise SweepError(f'{where}: {exc}') from None
    elif isinstance(item, dict):
        unknown = sorted(set(item) - set(ANATOMY_KEYS))
        if unknown or 'name' not in item:
            raise SweepError(f'{where}: expected a mapping with keys {list(ANATOMY_KEYS)} '
                             f'(name required), found keys {sorted(item)}')
        anatomy = study.Anatomy(
            str(item['name']),
            tuple(_strings(f'{where}.train', item.get('train', []), empty=True)),
            tuple(_strings(f'{where}.evaluate', item.get('evaluate', []), empty=True)),
            tuple(_path(d) for d in _strings(f'{where}.demos', item.get('demos', []),
                                             empty=True)))
    else:
        raise SweepError(f'{where}: expected an anatomy name, a path or a mapping, found '
                         f'{item!r}')
    if not NAME.fullmatch(anatomy.name):
        raise SweepError(f'{where}: expected a name of letters, digits, ".", "_" and "-", '
                         f'found {anatomy.name!r}')
    missing = [str(d) for d in anatomy.demos if not d.exists()]
    if missing:
        raise SweepError(f'{where}: expected existing demonstrations, found none at {missing}')
    return anatomy


def load_sweep(path: Path) -> study.StudyPlan:
    """The study plan of a sweep configuration, checked as the study checks its arguments.

    Raises:
        SweepError: an unreadable file, a missing or unknown key, a value of the wrong type or
            range, an unknown preset, anatomy or baseline; the message starts with the file.
    """
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise SweepError(f'{path}: expected a readable YAML file, found '
                         f'{type(exc).__name__}: {str(exc).splitlines()[0]}') from None
    try:
        return _plan(data)
    except study.StudyError as exc:
        raise SweepError(f'{path}: {exc}') from None


def _plan(data: Any) -> study.StudyPlan:
    if not isinstance(data, dict):
        raise SweepError(f'expected a mapping of {list(REQUIRED)} and optional '
                         f'{list(OPTIONAL)}, found {type(data).__name__}')
    unknown = sorted(set(data) - set(REQUIRED) - set(OPTIONAL))
    authors = data.get('authors_budgets', False)
    missing = [k for k in REQUIRED if k not in data and not (k == 'budgets' and authors)]
    if unknown or missing:
        raise SweepError(f'expected keys {list(REQUIRED)} and optional {list(OPTIONAL)}, found '
                         + ', '.join([f'unknown {unknown}'] * bool(unknown)
                                     + [f'no {missing}'] * bool(missing)))
    cfg = {**OPTIONAL, **data}
    for key in SWITCHES:
        if not isinstance(cfg[key], bool):
            raise SweepError(f'{key}: expected true or false, found {cfg[key]!r}')
    for key in ('trials', 'dynamic_steps', 'unseen_scenario_seed'):
        if not isinstance(cfg[key], int) or isinstance(cfg[key], bool):
            raise SweepError(f'{key}: expected an integer, found {cfg[key]!r}')
    modes = _strings('modes', cfg['modes'])
    if not set(modes) <= set(study.MODES):
        raise SweepError(f'modes: expected some of {list(study.MODES)}, found {modes}')
    baselines = _strings('baselines', cfg['baselines'], empty=True)
    if not set(baselines) <= set(BASELINES):
        raise SweepError(f'baselines: expected some of {list(BASELINES)}, found {baselines}')
    if not isinstance(cfg['anatomies'], list) or not cfg['anatomies']:
        raise SweepError(f'anatomies: expected a non-empty list, found {cfg["anatomies"]!r}')
    anatomies = [parse_anatomy(a, f'anatomies[{i}]') for i, a in enumerate(cfg['anatomies'])]
    names = [a.name for a in anatomies]
    if len(set(names)) != len(names):
        raise SweepError(f'anatomies: expected distinct names, found {names}')
    args = argparse.Namespace(
        methods=_strings('presets', cfg['presets']), seeds=_ints('seeds', cfg['seeds']),
        steps=_ints('budgets', cfg['budgets']) if 'budgets' in cfg else None, modes=modes,
        trials=cfg['trials'], dynamic_steps=cfg['dynamic_steps'],
        unseen_scenario_seed=cfg['unseen_scenario_seed'], baselines=baselines, jobs=1,
        demos=[], report_only=False, authors_budgets=cfg['authors_budgets'],
        fresh_budgets=cfg['fresh_budgets'])
    try:
        plan = study.check_args(args)
    except study.StudyError as exc:  # '--methods: ...' -> 'presets: ...'
        flag = {f'--{v.replace("_", "-")}': k for k, v in STUDY_FLAG.items()}
        head, _, rest = str(exc).partition(': ')
        raise SweepError(f'{flag.get(head, head)}: {rest}') from None
    return dataclasses.replace(plan, anatomies=tuple(anatomies))


# ------------------------------------------------------------------------------------------
# Ray: the executor, and the shared-filesystem check.


def run_logged(cmd: list[str], log: str, env: dict[str, str], cwd: str,
               driver_nice: int = 0) -> int:
    """The body of a Ray task: run ``cmd`` as a child process, output appended to ``log``
    (first a line when this worker runs at a higher niceness than ``driver_nice``, the sweep's);
    when the task is cancelled (KeyboardInterrupt in this worker), stop the child as the study
    does (SIGTERM, SIGKILL after 30 s). Returns its exit status."""
    with open(log, 'a') as f:
        if (nice := os.nice(0)) > driver_nice:
            f.write(f'sweep: this task runs at niceness {nice}, the sweep at {driver_nice} (the '
                    'Ray node was started without RAY_worker_niceness=0): slow beside other '
                    'work\n')
            f.flush()
        proc = subprocess.Popen(cmd, stdout=f, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, env=env, cwd=cwd)
    try:
        while True:  # short waits: the cancellation's KeyboardInterrupt lands between them
            with contextlib.suppress(subprocess.TimeoutExpired):
                return proc.wait(timeout=1.0)
    finally:
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def node_sees(probe: str, token: str, python: str) -> str:
    """On one node: '' when it reads ``token`` from the file ``probe``, can write beside it
    and has the interpreter ``python``; else what it lacks (a few words)."""
    path = Path(probe)
    try:
        if path.read_text() != token:
            return f'reads another {path} (not the same filesystem)'
    except OSError as exc:
        return f'cannot read {path} ({exc.strerror or type(exc).__name__})'
    reply = path.with_name(f'{path.name}.{uuid.uuid4().hex}')
    try:
        reply.write_text(token)
        reply.unlink()
    except OSError as exc:
        return f'cannot write in {path.parent} ({exc.strerror or type(exc).__name__})'
    if not Path(python).is_file():
        return f'has no interpreter {python} (the workspace is not at the same path)'
    return ''


class RayProcess:
    """A study task running as a Ray task (:class:`insilico_study.Process`)."""

    def __init__(self, ref: Any, log: Path) -> None:
        self.ref = ref
        self.log = log
        self.status: int | None = None

    def poll(self) -> int | None:
        import ray

        if self.status is None and ray.wait([self.ref], timeout=0)[0]:
            try:
                self.status = int(ray.get(self.ref))
            except ray.exceptions.TaskCancelledError:
                self.status = -15
            except ray.exceptions.RayError as exc:  # a worker or node lost: say so in the log
                with self.log.open('a') as f:
                    f.write(f'sweep: the Ray task ended without an exit status: '
                            f'{type(exc).__name__}: {str(exc).strip().splitlines()[0]}\n')
                self.status = -1
        return self.status

    def terminate(self) -> None:
        import ray

        ray.cancel(self.ref)  # KeyboardInterrupt in run_logged, which stops the process

    def wait(self, timeout: float | None = None) -> int:
        import ray

        if not ray.wait([self.ref], timeout=timeout)[0]:
            raise subprocess.TimeoutExpired('ray task', timeout or 0.0)
        status = self.poll()
        assert status is not None
        return status

    def kill(self) -> None:
        import ray

        ray.cancel(self.ref, force=True)


@contextlib.contextmanager
def ray_launcher(root: Path, address: str | None, num_cpus: int | None
                 ) -> Iterator[tuple[study.Launcher, int]]:
    """Start (local) or join (``address``) Ray, check that every node sees ``root``, and give
    a launcher of study tasks as Ray tasks and how many to run at a time (the cluster's CPUs).

    Raises:
        SweepError: local Ray not on 127.0.0.1, or a node that cannot see ``root``.
    """
    if address is None:
        os.environ.update(LOCAL_RAY)
    import ray
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    if __name__ != '__main__':  # imported (tests): ship our functions by value
        ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    if address is None:
        ray.init(address='local', num_cpus=num_cpus or os.cpu_count() or 1,
                 include_dashboard=False, log_to_driver=False, configure_logging=False)
    else:
        try:
            ray.init(address=address, log_to_driver=False, configure_logging=False)
        except (ConnectionError, RuntimeError) as exc:
            raise SweepError(
                f'--address {address}: expected a Ray cluster this process can join, found '
                f'none ({type(exc).__name__}: {str(exc).strip().splitlines()[0]}; with token '
                'authentication, RAY_AUTH_MODE=token and the cluster\'s token here too)'
            ) from None
    try:
        nodes = [n for n in ray.nodes() if n['Alive']]
        if address is None and {n['NodeManagerAddress'] for n in nodes} != {'127.0.0.1'}:
            raise SweepError(f'local Ray: expected it bound to 127.0.0.1, found '
                             f'{sorted(n["NodeManagerAddress"] for n in nodes)} (ray was '
                             'imported before the sweep set RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER)')
        token = uuid.uuid4().hex
        probe = root / f'.sweep_probe_{token}'
        probe.write_text(token)
        sees = ray.remote(num_cpus=0, max_retries=0)(node_sees)
        try:
            found = ray.get([sees.options(scheduling_strategy=NodeAffinitySchedulingStrategy(
                n['NodeID'], soft=False)).remote(str(probe), token, sys.executable)
                for n in nodes])
        finally:
            probe.unlink()
        for node, problem in zip(nodes, found, strict=True):
            if problem:
                raise SweepError(f'--out {root}: expected a folder every Ray node sees at the '
                                 f'same path (a shared filesystem), found node '
                                 f'{node["NodeManagerAddress"]} {problem}')
        task: Any = ray.remote(num_cpus=1, max_retries=0)(run_logged)  # (ray: its default arg)
        cwd, env, driver_nice = os.getcwd(), study.child_env(), os.nice(0)

        def launch(cmd: list[str], log: Path) -> study.Process:
            return RayProcess(task.remote(cmd, str(log), env, cwd, driver_nice), log)

        cpus = int(ray.cluster_resources().get('CPU', 1))
        study.say(f'Ray: {len(nodes)} node(s), {cpus} CPUs; every node sees {root}')
        yield launch, cpus
    finally:
        ray.shutdown()


# ------------------------------------------------------------------------------------------
# Command line.


def build_parser() -> argparse.ArgumentParser:
    """The sweep's command line."""
    p = argparse.ArgumentParser(prog='sweep', description=__doc__.split('\n')[0])
    p.add_argument('config', type=Path, help='sweep configuration (YAML; bench/sweeps/)')
    p.add_argument('--out', type=Path, default=None,
                   help='run folder (default runs/sweep_<config name>); on a cluster, a path '
                        'every node sees')
    p.add_argument('--address', default=None, metavar='HOST:PORT',
                   help='a running Ray cluster (its head); default: start a local Ray')
    p.add_argument('--num-cpus', type=int, default=None,
                   help='CPUs of the local Ray (default: all); tasks run one per CPU')
    p.add_argument('--no-ray', action='store_true',
                   help="run the tasks as the study does, local processes (--num-cpus at a "
                        "time), without Ray")
    p.add_argument('--progress-every', type=float, default=60.0,
                   help='seconds between progress lines of the running trainings')
    p.add_argument('--report-only', action='store_true',
                   help='rebuild OUT/report.md and results.csv from what exists; run nothing')
    return p


def command_line(args: argparse.Namespace, out: Path) -> str:
    """The command that re-runs this sweep."""
    def rel(p: Path) -> str:
        p = p.resolve()
        return str(p.relative_to(WS)) if p.is_relative_to(WS) else str(p)

    parts = ['scripts/ws', 'python', 'bench/sweep.py', rel(args.config), '--out', rel(out)]
    if args.address:
        parts += ['--address', args.address]
    elif args.num_cpus:
        parts += ['--num-cpus', str(args.num_cpus)]
    return shlex.join(parts + ['--no-ray'] * args.no_ray)


def main(argv: list[str] | None = None) -> int:
    """Entry point."""
    args = build_parser().parse_args(argv)
    try:
        if args.num_cpus is not None and args.num_cpus < 1:
            raise SweepError(f'--num-cpus: expected >= 1, found {args.num_cpus}')
        if args.address is not None and (args.num_cpus is not None or args.no_ray):
            raise SweepError('--address: expected neither --num-cpus nor --no-ray with a '
                             'cluster (its nodes say how many CPUs it has)')
        plan = load_sweep(args.config)
    except study.StudyError as exc:
        print(f'sweep: error: {exc}', file=sys.stderr)
        return 2
    out = (args.out or Path('runs') / f'sweep_{args.config.stem}').resolve()
    layout = study.Layout(out, plan.fresh)
    command = command_line(args, out)
    study.note_left_out(layout, plan)
    if args.report_only:
        study.say(f'report: {study.write_report(layout, plan, command)}')
        return 0
    t0 = time.monotonic()
    try:
        with study.study_lock(out):
            if args.no_ray or all(t.done() for t in study.plan_tasks(layout, plan)):
                if not args.no_ray:
                    study.say('every task is done: no Ray needed')
                return study.run_study(layout, plan, command, args.num_cpus or 1,
                                       args.progress_every)
            with ray_launcher(out, args.address, args.num_cpus) as (launch, cpus):
                study.say(f'Ray up in {study.format_duration(time.monotonic() - t0)}')
                return study.run_study(layout, plan, command, cpus, args.progress_every,
                                       launch)
    except study.StudyError as exc:
        print(f'sweep: error: {exc}', file=sys.stderr)
        return 2


if __name__ == '__main__':
    sys.exit(main())
