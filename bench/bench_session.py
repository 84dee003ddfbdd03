#!/usr/bin/env python3
"""The main job's speed: real time per core of a trial, and ``bash scripts/demo.sh`` timed.

    python3 bench/bench_session.py [--trials 1] [--profile N]        # real time per core
    python3 bench/bench_session.py --demo [--runs 2] [--trials 30] [--busy 0] [-- session args]

**Real time per core** (the default). Runs ``--trials`` trials of each condition of the main
job (default anatomy, rigid phantom, the committed C-GAIL policy, the true plant of seed 0 with
the controller's nominal model: a trial costs the same with the identified one) one after the
other in this process, each on its own rig exactly as a worker of ``cgail session`` runs it
(after one warm-up trial that is not counted), and prints per trial the simulated seconds (the
lockstep clock: settle, trial and tail), the CPU seconds of the process (every thread: the
nodes, the simulated Aurora's pty thread, the recorder's writer, DDS) and the wall seconds;
then **real time per core** = simulated seconds per CPU second, which is the simulated seconds
per wall second per core of a worker that has its core to itself (target: >= 25). CPU time
does not depend on what else runs on the machine, so the figure holds on a loaded host too.
``--profile N`` also profiles the trials with cProfile (the main thread, where the nodes run;
profiling slows Python code about twofold) and prints the N functions with the most own time
and the N with the most cumulative time.

**The demo** (``--demo``). Runs the main-job command (README, docs/tutorials/simulated-session.md)
``bash scripts/demo.sh --out <tmp>/run<k> --trials <n>`` (setup check, identification, then
the simulated in-vitro session) ``--runs`` times, and prints for each run the wall time of the
whole command and of the trials, the simulated trial time, real time overall and per core
(simulated seconds per wall second of the trials, over the workers), and the phases (setup,
the session's start, identification, trials and report, from their printed lines; the main job's
bar is the time after setup); then whether the runs
printed identical metrics tables and recorded identical bags (message counts and content), and
the bags' total size. ``--busy N`` keeps N busy-loop processes running during every run after
the first (the results must not change). Load average before each run is printed.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path
import re
import subprocess
import sys
import tempfile
import time

WS = Path(__file__).resolve().parents[1]


def tables(stdout: str) -> str:
    """The printed metrics tables (from '## Trials' on), without the wall-time lines."""
    start = stdout.find('## Trials')
    return '\n'.join(line for line in stdout[start:].splitlines()
                     if not line.startswith('cgail session: '))


def phases(stdout: str, stderr: str, wall: float) -> str:
    """Where the demo's wall time went: setup (``[setup Ns] ready``), then the session's own
    phases (its ``phases:`` line: start, identification, trials, report) and what is left
    (the interpreter's start and exit)."""
    m = re.search(r'\[setup\s+(\d+)s\] ready', stderr + stdout)
    setup = float(m.group(1)) if m else float('nan')
    found = dict(re.findall(r'(start|identification|trials|report) ([\d.]+) s',
                            stdout[stdout.rfind('phases:'):] if 'phases:' in stdout else ''))
    parts = {k: float(v) for k, v in found.items()}
    rest = wall - setup - sum(parts.values())
    return ('phases: setup ' + f'{setup:.0f} s, ' + ', '.join(
        f'{k} {v:.1f} s' for k, v in parts.items()) + f', other {rest:.1f} s'
        + f'; after setup {wall - setup:.1f} s')


def digests(out: Path) -> dict[str, object]:
    code = ('import json, sys; from pathlib import Path; '
            'from cgail_bags.bagio import content_digest; '
            'print(json.dumps({b.name: content_digest(b) '
            'for b in sorted(Path(sys.argv[1]).glob("bags/*/*"))}))')
    done = subprocess.run([str(WS / 'scripts' / 'ws'), 'python', '-c', code, str(out)],
                          capture_output=True, text=True, check=True)
    result: dict[str, object] = json.loads(done.stdout)
    return result


def bag_bytes(out: Path) -> int:
    """Total size of the session's bags."""
    return sum(f.stat().st_size for f in (out / 'bags').rglob('*') if f.is_file())


def per_core(trials: int, profile: int) -> int:
    """Real time per core of ``trials`` trials per condition, in this process (module
    docstring)."""
    import cProfile
    import pstats

    from cgail_rig import session as s
    from cgail_rig.domain import reserve_domain

    lease = reserve_domain()
    settings = s.SessionSettings(policy=str(s.default_policy()), plant='true', plant_seed=0)
    prof = cProfile.Profile() if profile else None
    sim_total = cpu_total = wall_total = 0.0
    with tempfile.TemporaryDirectory(prefix='bench_session_') as tmp:
        try:
            warm = s.plan_trials(['cgail'], 1, 0, Path(tmp) / 'warm')[0]
            s.run_trial(settings, warm, lease.domain_id)  # imports, caches, policy load
            for spec in s.plan_trials(s.CONDITIONS, trials, 0, Path(tmp) / 'bags'):
                cpu0, wall0 = time.process_time(), time.monotonic()
                if prof is not None:
                    prof.enable()
                result = s.run_trial(settings, spec, lease.domain_id)
                if prof is not None:
                    prof.disable()
                cpu, wall = time.process_time() - cpu0, time.monotonic() - wall0
                sim = result.ticks / settings.physics_rate
                if result.failed:
                    print(f'{spec.label}: {result.outcome}')
                    return 1
                sim_total, cpu_total, wall_total = (sim_total + sim, cpu_total + cpu,
                                                    wall_total + wall)
                print(f'{spec.label:<14} {result.outcome:<34} {sim:6.1f} s simulated, '
                      f'{cpu:5.2f} s CPU, {wall:5.2f} s wall: {sim / cpu:5.1f}x real time '
                      f'per core', flush=True)
            n = 2 * trials
            print(f'real time per core: {sim_total / cpu_total:.1f}x ({sim_total:.0f} s '
                  f'simulated in {cpu_total:.1f} s CPU, {wall_total:.1f} s wall, load '
                  f'{os.getloadavg()[0]:.1f}; bags {bag_bytes(Path(tmp)) / n / 1e6:.1f} MB '
                  f'per trial)')
        finally:
            lease.release()
    if prof is not None:
        stats = pstats.Stats(prof)
        for key in ('tottime', 'cumulative'):
            print(f'\n--- profile of the trials, by {key} (main thread) ---')
            stats.sort_stats(key).print_stats(profile)
    return 0


def demo(runs: int, trials: int, busy_loops: int, extra: list[str]) -> int:
    """The main-job command timed ``runs`` times (module docstring)."""
    results = []
    with tempfile.TemporaryDirectory(prefix='bench_session_') as tmp:
        for k in range(runs):
            out = Path(tmp) / f'run{k + 1}'
            busy = [subprocess.Popen([sys.executable, '-c', 'while True: pass'])
                    for _ in range(busy_loops if k > 0 else 0)]
            load = os.getloadavg()[0]
            t0 = time.monotonic()
            try:
                done = subprocess.run(
                    ['bash', str(WS / 'scripts' / 'demo.sh'), '--out', str(out), '--trials',
                     str(trials), *extra], capture_output=True, text=True, check=False)
            finally:
                for p in busy:
                    p.kill()
                    p.wait()
            wall = time.monotonic() - t0
            if done.returncode != 0:
                print(done.stdout[-3000:], done.stderr[-3000:], sep='\n')
                print(f'run {k + 1}: demo.sh exited with {done.returncode}')
                return 1
            trial_walls = [float(m) for m in re.findall(r'\(\s*([\d.]+) s wall, domain',
                                                        done.stdout)]
            sim = [float(m) for m in re.findall(r' T\s+([\d.]+) s ', done.stdout)]
            m = re.search(r'trials in (\d+):(\d+) on (\d+) worker', done.stdout)
            session_wall = int(m.group(1)) * 60 + int(m.group(2)) if m else float('nan')
            jobs = int(m.group(3)) if m else 1
            print(f'run {k + 1}: load {load:.1f} before, {len(busy)} busy loops; demo.sh '
                  f'{wall:.1f} s wall (trials {session_wall:.0f} s on {jobs} worker(s)); '
                  f'{len(sim)} trials, {sum(sim):.0f} s simulated, '
                  f'{sum(sim) / session_wall:.1f}x real time overall, '
                  f'{sum(sim) / session_wall / jobs:.1f}x per core; per trial '
                  f'{min(trial_walls):.1f}-{max(trial_walls):.1f} s wall; bags '
                  f'{bag_bytes(out) / 1e6:.0f} MB', flush=True)
            print(f'run {k + 1}: {phases(done.stdout, done.stderr, wall)}', flush=True)
            results.append((tables(done.stdout), digests(out), done.stdout))
        same_tables = all(r[0] == results[0][0] for r in results)
        same_bags = all(r[1] == results[0][1] for r in results)
        print(f'identical metrics tables across the {runs} runs: '
              f'{"yes" if same_tables else "NO"}')
        print(f'identical bags (message counts and content) across the runs: '
              f'{"yes" if same_bags else "NO"} ({len(results[0][1])} bags)')
        print()
        print(results[0][0])
    return 0 if same_tables and same_bags else 1


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or '').split('\n')[0])
    parser.add_argument('--trials', type=int, default=None,
                        help='trials per condition (default 1; with --demo 30, the main job)')
    parser.add_argument('--profile', type=int, default=0, metavar='N',
                        help='also profile the trials and print the top N functions')
    parser.add_argument('--demo', action='store_true',
                        help='time bash scripts/demo.sh instead (the whole main job)')
    parser.add_argument('--runs', type=int, default=2, help='--demo: runs of the command')
    parser.add_argument('--busy', type=int, default=0,
                        help='--demo: busy-loop processes during the runs after the first')
    parser.add_argument('extra', nargs='*', help='--demo: more cgail session arguments (after '
                                                 '--)')
    args = parser.parse_args()
    if args.demo:
        return demo(args.runs, args.trials or 30, args.busy, args.extra)
    return per_core(args.trials or 1, args.profile)


if __name__ == '__main__':
    sys.exit(main())
