#!/usr/bin/env python3
"""Autonomous soak: trial after trial of the autonomy with faults injected, memory and CPU flat?

    python3 bench/bench_autonomy_soak.py [--minutes 60] [--conditions autonomous shared]
        [--faults dropout stuck_pam slipping_sleeve wall_push none] [--mode static] [--seed 0]
        [--detail]

Runs trials of the session's autonomy conditions (``cgail_rig.session``: default anatomy, the
committed C-GAIL policy, the true plant of ``--seed`` with the controller's nominal model) one
after the other **in this process**, each on its own rig exactly as a worker of ``cgail session``
runs it, for ``--minutes`` of wall time (default 60: the issue's one-hour soak). Trial ``k``
cycles through ``--conditions`` and ``--faults`` (``none``: a trial without a fault) with its
own seed, so faults are injected throughout. After each trial it prints the trial's end state
(``done`` with the arrival, or ``stopped:<reason>``; a fault's detection time), its simulated
seconds, the process's CPU seconds and the resident memory (RSS, from ``/proc/self/status``)
after the trial's rig was closed.

At the end: whether every trial ended in a defined state (``done``, ``stopped:<reason>`` or
the time limit, never a rig error), whether every injected fault was caught within its bound
(a stuck PAM never observable, the chamber asked only for what it held, is no miss), and
whether memory and CPU per trial stayed flat: the slope of a least-squares line through RSS
against trial index (after the first ``--warmup`` trials, which load caches), in MB per
100 trials, and through CPU seconds per simulated second against trial index, in percent of
the mean per 100 trials. Flat: the RSS slope below ``--max-rss-slope`` MB per 100 trials and
the CPU slope below ``--max-cpu-slope`` % (the RSS slope over the whole run after warm-up and
over its second half, so that growth late in the run is not averaged away by a level reached
early: glibc's free lists fill over the first hundred or so trials). Exit status 1 if a trial
failed or either is not flat.

``--detail`` says where the memory is after each trial (anonymous, file-backed and shared-memory
pages; glibc's heap in use and free; mappings, threads, open files) and their slopes at the end.
(Each trial's rig hands glibc's free heap back when it closes: ``cgail_rig.session``.)
"""

from __future__ import annotations

import argparse
from array import array
from dataclasses import replace
import math
import os
from pathlib import Path
import sys
import tempfile
import time


def rss_mb() -> float:
    """Resident set size of this process, MB."""
    for line in Path('/proc/self/status').read_text().splitlines():
        if line.startswith('VmRSS:'):
            return int(line.split()[1]) / 1024.0
    return math.nan


def memory_detail() -> dict[str, float]:
    """Where the resident memory is: ``/proc/self/smaps_rollup`` (anonymous, file-backed and
    shared-memory KB as MB), glibc's ``mallinfo2`` (bytes in use and free inside the heap and
    its arenas, MB), and the counts of memory mappings, threads and open files."""
    out: dict[str, float] = {}
    for line in Path('/proc/self/smaps_rollup').read_text().splitlines()[1:]:
        key, _, rest = line.partition(':')
        if key in ('Anonymous', 'Pss_File', 'Pss_Shmem'):
            out[key] = int(rest.split()[0]) / 1024.0
    info = _mallinfo2()
    if info is not None:
        out['heap_used'] = info.uordblks / 2**20
        out['heap_free'] = info.fordblks / 2**20
        out['mmapped'] = info.hblkhd / 2**20
        out['arena'] = info.arena / 2**20
    out['maps'] = float(len(Path('/proc/self/maps').read_text().splitlines()))
    out['threads'] = float(len(os.listdir('/proc/self/task')))
    out['fds'] = float(len(os.listdir('/proc/self/fd')))
    return out


def _mallinfo2():  # (a ctypes structure, or None off glibc >= 2.33)
    import ctypes

    class MallInfo2(ctypes.Structure):
        _fields_ = [(name, ctypes.c_size_t) for name in (
            'arena', 'ordblks', 'smblks', 'hblks', 'hblkhd', 'usmblks', 'fsmblks',
            'uordblks', 'fordblks', 'keepcost')]
    try:
        libc = ctypes.CDLL('libc.so.6')
        libc.mallinfo2.restype = MallInfo2
    except (OSError, AttributeError):
        return None
    return libc.mallinfo2()


def slope(ys: list[float]) -> float:
    """Least-squares slope of ``ys`` against their index (0 for fewer than 2)."""
    n = len(ys)
    if n < 2:
        return 0.0
    mx = (n - 1) / 2.0
    my = sum(ys) / n
    sxx = sum((i - mx) ** 2 for i in range(n))
    return sum((i - mx) * (y - my) for i, y in enumerate(ys)) / sxx


def main(argv: list[str] | None = None) -> int:
    from cgail_rig import session as s
    from cgail_rig.core.faults import FAULT_KINDS

    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('--minutes', type=float, default=60.0, help='wall minutes (default 60)')
    p.add_argument('--conditions', nargs='+', choices=s.AUTONOMY_CONDITIONS,
                   default=['autonomous', 'shared'], help='conditions, in turn')
    p.add_argument('--faults', nargs='+', choices=(*FAULT_KINDS, 'none'),
                   default=[*FAULT_KINDS, 'none'], help='faults, in turn (none: no fault)')
    p.add_argument('--mode', choices=('static', 'dynamic'), default='static')
    p.add_argument('--seed', type=int, default=0, help='plant and trial seeds')
    p.add_argument('--time-limit', type=float, default=180.0, help='trial limit, simulated s')
    p.add_argument('--warmup', type=int, default=2, help='trials left out of the slopes')
    p.add_argument('--detail', action='store_true',
                   help='also print where the memory is after each trial (anonymous, file, '
                        'shared memory, glibc heap in use and free, mappings, threads, files)')
    p.add_argument('--max-rss-slope', type=float, default=5.0,
                   help='flat: RSS grows less than this, MB per 100 trials (default 5)')
    p.add_argument('--max-cpu-slope', type=float, default=10.0,
                   help='flat: CPU per simulated second grows less than this, %% of its mean '
                        'per 100 trials (default 10)')
    args = p.parse_args(argv)
    s.limit_heap_arenas()  # (before the domain probe's middleware threads, as the session does)
    if not args.minutes > 0.0:
        print(f'bench_autonomy_soak: error: --minutes must be > 0, found {args.minutes}',
              file=sys.stderr)
        return 2
    if not os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE'):
        print('bench_autonomy_soak: error: ROS_AUTOMATIC_DISCOVERY_RANGE is unset; run '
              'through scripts/ws', file=sys.stderr)
        return 2
    from cgail_rig.domain import reserve_domain

    settings = s.SessionSettings(policy=str(s.default_policy('default', args.mode)),
                                 mode=args.mode, plant='true', plant_seed=args.seed,
                                 time_limit=args.time_limit)
    lease = reserve_domain()
    print(f'bench_autonomy_soak: {args.minutes:g} min of {", ".join(args.conditions)} '
          f'({args.mode}) with faults {", ".join(args.faults)}; ROS domain {lease.domain_id}; '
          f'load {os.getloadavg()[0]:.1f}', flush=True)
    # Per-trial figures in flat arrays of doubles (8 bytes a value): a list of tuples or of
    # dicts would itself grow the heap ~1 KB a trial and show up in the slopes it measures.
    rss_col, cpu_col, sim_col = array('d'), array('d'), array('d')
    undefined, missed = [], []
    details: dict[str, array] = {}
    end = time.monotonic() + args.minutes * 60.0
    k = 0
    with tempfile.TemporaryDirectory(prefix='autonomy_soak_') as tmp:
        try:
            while time.monotonic() < end:
                condition = args.conditions[k % len(args.conditions)]
                fault = args.faults[k % len(args.faults)]
                index = k // len(args.conditions)
                spec = replace(s.plan_trials([condition], index + 1, args.seed,
                                             Path(tmp) / 'bags')[index],
                               fault='' if fault == 'none' else fault)
                cpu0 = time.process_time()
                result = s.run_trial(settings, spec, lease.domain_id)
                cpu = time.process_time() - cpu0
                sim = result.ticks / settings.physics_rate
                rss = rss_mb()
                rss_col.append(rss)
                cpu_col.append(cpu)
                sim_col.append(sim)
                for bag in Path(tmp, 'bags').rglob('*.mcap'):
                    bag.unlink()  # (an hour of bags would fill a small disk)
                state = result.outcome
                defined = not result.failed and (
                    state.startswith(('stopped:', 'time limit', 'at the target',
                                      'closest approach')))
                if not defined:
                    undefined.append(f'{spec.label}: {state}')
                detail = ''
                if result.fault is not None:
                    f = result.fault
                    detail = (f'  fault {f.kind}: ' + (f'caught in {f.detection_s:.3f} s'
                              if f.caught else ('not reached' if not f.injected
                                                else 'never observable' if f.never_observable
                                                else 'MISSED')))
                    if f.missed:
                        missed.append(f'{spec.label} {f.kind}')
                print(f'[{k + 1:4d}] {spec.label:<20} {state[:60]:<60} {sim:6.1f} s sim  '
                      f'{cpu:5.2f} s CPU  RSS {rss:7.1f} MB{detail}', flush=True)
                if args.detail:
                    mem = memory_detail()
                    for key, value in mem.items():
                        details.setdefault(key, array('d')).append(value)
                    print('       ' + '  '.join(f'{key} {value:.1f}' for key, value
                                                in mem.items()), flush=True)
                k += 1
        finally:
            lease.release()
    rows = list(zip(rss_col, cpu_col, sim_col, strict=True))  # (RSS MB, CPU s, simulated s)
    used = rows[args.warmup:] if len(rows) > args.warmup + 1 else rows
    rss_slope = slope([r[0] for r in used]) * 100.0
    late = [r[0] for r in used[len(used) // 2:]]
    late_slope = slope(late) * 100.0  # (a level reached early, or still climbing at the end?)
    quarters = [used[i * len(used) // 4:(i + 1) * len(used) // 4] for i in range(4)]
    per_sim = [r[1] / r[2] for r in used if r[2] > 0.0]
    mean = sum(per_sim) / len(per_sim) if per_sim else math.nan
    cpu_slope = slope(per_sim) * 100.0 / mean * 100.0 if per_sim else math.nan
    flat_rss = rss_slope < args.max_rss_slope and late_slope < args.max_rss_slope
    flat_cpu = cpu_slope < args.max_cpu_slope
    print(f'\n{k} trials; end states defined: {k - len(undefined)}/{k}'
          + (f' (undefined: {"; ".join(undefined)})' if undefined else ''))
    print(f'faults missed: {len(missed)}' + (f' ({"; ".join(missed)})' if missed else ''))
    print(f'RSS: {rows[0][0]:.1f} MB after trial 1, {rows[-1][0]:.1f} MB after trial {k}; '
          f'slope {rss_slope:+.2f} MB per 100 trials (after {args.warmup} warm-up), '
          f'{late_slope:+.2f} over the second half; mean per quarter '
          + ' / '.join(f'{sum(r[0] for r in q) / len(q):.1f}' for q in quarters if q)
          + f' MB: {"flat" if flat_rss else "GROWING"}' if rows else 'RSS: no trial')
    if details and len(rss_col) > args.warmup + 1:  # (details: one value a trial, as rss_col)
        print('memory slopes per 100 trials: ' + ', '.join(
            f'{key} {slope(list(column[args.warmup:])) * 100.0:+.2f}'
            for key, column in details.items()))
    print(f'CPU per simulated second: mean {mean:.4f} s/s; slope {cpu_slope:+.2f} % of the '
          f'mean per 100 trials: {"flat" if flat_cpu else "GROWING"}')
    return 0 if rows and not undefined and flat_rss and flat_cpu else 1


if __name__ == '__main__':
    sys.exit(main())
