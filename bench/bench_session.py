#!/usr/bin/env python3
"""The main job's wall time and reproducibility: ``bash scripts/demo.sh`` twice (target <= 2 min).

    python3 bench/bench_session.py [--runs 2] [--trials 10] [--busy 0] [-- extra session args]

Runs the main-job command (README, docs/tutorials/simulated-session.md)
``bash scripts/demo.sh --out <tmp>/run<k>`` (setup check,
then the simulated in-vitro session: 10 C-GAIL and 10 centerline trials on the built-in
defaults) ``--runs`` times, and prints for each run the wall time of the whole command and of
the session, the simulated trial time and the speed-up over real time; then whether the runs
printed identical metrics tables and recorded identical bags (message counts and content).
``--busy N`` keeps N busy-loop processes running during every run after the first (the
results must not change). Load average before each run is printed.
"""

from __future__ import annotations

import argparse
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
                     if not line.startswith('cgail session: wrote'))


def digests(out: Path) -> dict[str, object]:
    code = ('import json, sys; from pathlib import Path; '
            'from cgail_bags.bagio import content_digest; '
            'print(json.dumps({b.name: content_digest(b) '
            'for b in sorted(Path(sys.argv[1]).glob("bags/*/*"))}))')
    done = subprocess.run([str(WS / 'scripts' / 'ws'), 'python', '-c', code, str(out)],
                          capture_output=True, text=True, check=True)
    import json

    return json.loads(done.stdout)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--runs', type=int, default=2)
    parser.add_argument('--trials', type=int, default=10, help='trials per condition')
    parser.add_argument('--busy', type=int, default=0,
                        help='busy-loop processes during the runs after the first')
    parser.add_argument('extra', nargs='*', help='more cgail session arguments (after --)')
    args = parser.parse_args()
    results = []
    with tempfile.TemporaryDirectory(prefix='bench_session_') as tmp:
        for k in range(args.runs):
            out = Path(tmp) / f'run{k + 1}'
            busy = [subprocess.Popen([sys.executable, '-c', 'while True: pass'])
                    for _ in range(args.busy if k > 0 else 0)]
            load = os.getloadavg()[0]
            t0 = time.monotonic()
            try:
                done = subprocess.run(
                    ['bash', str(WS / 'scripts' / 'demo.sh'), '--out', str(out), '--trials',
                     str(args.trials), *args.extra], capture_output=True, text=True, check=False)
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
            session_wall = float(re.findall(r'\((\d+) s wall\)\s*$', done.stdout.strip())[-1])
            jobs = re.search(r'on (\d+) worker processes|on ROS domain', done.stdout)
            print(f'run {k + 1}: load {load:.1f} before, {len(busy)} busy loops; demo.sh '
                  f'{wall:.1f} s wall (session {session_wall:.0f} s, '
                  f'{jobs.group(1) if jobs and jobs.group(1) else 1} job(s)); {len(sim)} '
                  f'trials, {sum(sim):.0f} s simulated, {sum(sim) / session_wall:.1f}x real '
                  f'time overall; per trial {min(trial_walls):.1f}-{max(trial_walls):.1f} s '
                  f'wall', flush=True)
            results.append((tables(done.stdout), digests(out), done.stdout))
        same_tables = all(r[0] == results[0][0] for r in results)
        same_bags = all(r[1] == results[0][1] for r in results)
        print(f'identical metrics tables across the {args.runs} runs: '
              f'{"yes" if same_tables else "NO"}')
        print(f'identical bags (message counts and content) across the runs: '
              f'{"yes" if same_bags else "NO"} ({len(results[0][1])} bags)')
        print()
        print(results[0][0])
    return 0 if same_tables and same_bags else 1


if __name__ == '__main__':
    sys.exit(main())
