"""``evaluate``: the paper's in-silico experiments as a markdown report with box plots.

Example::

    scripts/ws evaluate --policy C-GAIL=models/cgail_default.onnx --policy GAIL=runs/gail.onnx \
        --baselines centerline expert --modes static dynamic --trials 100 --out reports/insilico

Each method runs ``--trials`` episodes; trial k uses start ``k % 3``, target ``(k // 3) % 5`` and
env seed ``seed + k``, so every method sees the same start x target sequence. Metrics (paper
Sec. IV-C): success rate delta (tip within epsilon = 10 mm of the target), timesteps T_s (all
trials and successful ones), targeting error T_a (minimum tip-target distance, mm; all trials and
successful ones). Kruskal-Wallis tests (p < 0.05) compare the methods on T_s and T_a.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
import sys
import time
from typing import Any

import numpy as np

from cgail_planner.learning.errors import LearningError
from cgail_planner.learning.onnx_policy import OnnxPolicy

Policy = Callable[[np.ndarray], np.ndarray]


@dataclass
class Trial:
    """Outcome of one evaluation episode."""

    success: bool
    collision: bool
    timesteps: int
    targeting_error_mm: float


class CenterlineFollower:
    """Baseline: pure pursuit of the target branch's centerline, then of the target."""

    def __init__(self, env: Any, lookahead: int = 6, approach: float = 0.035) -> None:
        self.env = env.unwrapped
        self.lookahead, self.approach = lookahead, approach
        self.progress = 0

    def reset(self, seed: int | None = None) -> None:
        """New episode."""
        self.progress = 0

    def act(self) -> np.ndarray:
        """Steer at the carrot (lookahead waypoints past the furthest reached one)."""
        from cgail_planner.sim.catheter import steer_towards

        eng = self.env.engine
        p, R = eng.catheter.tip_position[0], eng.catheter.tip_rotation[0]
        wps = eng.waypoints[0]
        self.progress = max(self.progress, int(np.argmin(np.linalg.norm(wps - p, axis=1))))
        k = min(self.progress + self.lookahead, len(wps) - 1)
        target = eng.target[0]
        carrot = target if (np.linalg.norm(target - p) < self.approach
                            or k >= len(wps) - 2) else wps[k]
        return steer_towards(p, R, carrot, eng.config.catheter,
                             eng.catheter.theta_max).astype(np.float32)


def run_trials(env: Any, method: Any, trials: int, seed: int,
               reuse_pairs: bool = False) -> list[Trial]:
    """``trials`` episodes of a policy (obs -> action) or a state-based baseline (``act()``).

    With ``reuse_pairs`` (static mode, deterministic method: the rigid-wall simulator and the
    method are then deterministic functions of the start/target pair, which the demo
    re-simulation check verifies to 1 micrometre) each start x target pair is simulated once
    and its outcome counted for every trial that uses it.
    """
    sc = env.unwrapped.engine.scenarios
    n_s, n_t = len(sc.starts), len(sc.targets)
    out: list[Trial] = []
    done: dict[tuple[int, int], Trial] = {}
    for k in range(trials):
        pair = (k % n_s, (k // n_s) % n_t)
        if reuse_pairs and pair in done:
            out.append(done[pair])
            continue
        obs, _ = env.reset(seed=seed + k, options={'start': pair[0], 'target': pair[1]})
        if hasattr(method, 'reset'):
            method.reset(seed + k)
        while True:
            a = method.act() if hasattr(method, 'act') else method(obs)
            obs, _, te, tr, info = env.step(a)
            if te or tr:
                break
        out.append(Trial(bool(info['success']), bool(info['collision']), int(info['timesteps']),
                         1e3 * float(info['targeting_error'])))
        done[pair] = out[-1]
    return out


def summarize(trials: list[Trial]) -> dict[str, float]:
    """Success rate, T_s and T_a (all and successful) of a method."""
    succ = [t for t in trials if t.success]

    def med(xs: list[float]) -> float:
        return float(np.median(xs)) if xs else float('nan')

    return {
        'n': len(trials), 'success_rate': float(np.mean([t.success for t in trials])),
        'collision_rate': float(np.mean([t.collision for t in trials])),
        'T_s_all': med([t.timesteps for t in trials]),
        'T_s_succ': med([t.timesteps for t in succ]),
        'T_a_all_mm': med([t.targeting_error_mm for t in trials]),
        'T_a_succ_mm': med([t.targeting_error_mm for t in succ]),
    }


def kruskal(groups: dict[str, list[float]]) -> float:
    """Kruskal-Wallis p-value over the non-empty groups (nan with fewer than two)."""
    from scipy.stats import kruskal as kw

    vals = [np.asarray(v) for v in groups.values() if len(v) > 0]
    if len(vals) < 2 or all(np.all(v == vals[0][0]) for v in vals):
        return float('nan')
    return float(kw(*vals).pvalue)


def boxplot(results: dict[str, list[Trial]], metric: str, title: str, path: Path) -> None:
    """Box plot of one metric per method (paper Fig. 6/7 style)."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    names = list(results)
    data = [[getattr(t, metric) for t in results[n]] for n in names]
    fig, ax = plt.subplots(figsize=(1.6 * len(names) + 2, 4))
    ax.boxplot(data, tick_labels=names)
    ax.set_title(title)
    ax.set_ylabel({'timesteps': 'T_s (steps)', 'targeting_error_mm': 'T_a (mm)'}[metric])
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def write_report(all_results: dict[str, dict[str, list[Trial]]], out: Path,
                 notes: str = '') -> Path:
    """Markdown report with one table per mode, KW p-values and the box plots."""
    out.mkdir(parents=True, exist_ok=True)
    lines = ['# In-silico evaluation', '', notes, '']
    for mode, results in all_results.items():
        lines += [f'## {mode}', '',
                  '| method | n | success | collision | T_s all | T_s succ | T_a all (mm) | '
                  'T_a succ (mm) |', '|---|---|---|---|---|---|---|---|']
        for name, trials in results.items():
            s = summarize(trials)
            lines.append(f"| {name} | {s['n']} | {100 * s['success_rate']:.0f}% | "
                         f"{100 * s['collision_rate']:.0f}% | {s['T_s_all']:.0f} | "
                         f"{s['T_s_succ']:.0f} | {s['T_a_all_mm']:.1f} | "
                         f"{s['T_a_succ_mm']:.1f} |")
        p_ts = kruskal({n: [t.timesteps for t in tr if t.success] for n, tr in results.items()})
        p_ta = kruskal({n: [t.targeting_error_mm for t in tr] for n, tr in results.items()})
        lines += ['', '(medians; T_s/T_a "succ" over successful trials only)', '',
                  f'Kruskal-Wallis across methods: T_s (successful) p = {p_ts:.3g}; '
                  f'T_a (all) p = {p_ta:.3g}.', '']
        first = next(iter(results))
        for other in list(results)[1:]:
            pa = kruskal({first: [t.targeting_error_mm for t in results[first]],
                          other: [t.targeting_error_mm for t in results[other]]})
            lines.append(f'- {first} vs {other}: T_a p = {pa:.3g}')
        for metric, label in (('timesteps', 'T_s'), ('targeting_error_mm', 'T_a')):
            png = f'{mode}_{label}.png'
            boxplot(results, metric, f'{label} ({mode})', out / png)
            lines += ['', f'![{label} {mode}]({png})']
        lines.append('')
    path = out / 'report.md'
    path.write_text('\n'.join(lines) + '\n')
    return path


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``evaluate``."""
    p = argparse.ArgumentParser(prog='evaluate', description=__doc__.split('\n')[0])
    p.add_argument('--policy', action='append', default=[], metavar='NAME=PATH.onnx',
                   help='a learned policy to evaluate (repeatable)')
    p.add_argument('--baselines', nargs='*', default=['centerline', 'expert'],
                   choices=('centerline', 'expert'))
    p.add_argument('--modes', nargs='+', default=['static'], choices=('static', 'dynamic'))
    p.add_argument('--anatomy', default='default')
    p.add_argument('--trials', type=int, default=100)
    p.add_argument('--seed', type=int, default=1000)
    p.add_argument('--out', type=Path, default=Path('reports/insilico'))
    args = p.parse_args(argv)
    from cgail_planner.learning.expert import ScriptedExpert
    from cgail_planner.sim.config import EnvConfig
    from cgail_planner.sim.env import CatheterNavEnv

    try:
        policies: dict[str, Any] = {}
        for spec in args.policy:
            name, sep, path = spec.partition('=')
            if not sep:
                raise LearningError(f'--policy expects NAME=PATH.onnx, found {spec!r}')
            policies[name] = OnnxPolicy(path)
        all_results: dict[str, dict[str, list[Trial]]] = {}
        for mode in args.modes:
            env = CatheterNavEnv(EnvConfig(mode=mode, anatomy=args.anatomy))
            methods: dict[str, Any] = dict(policies)
            if 'centerline' in args.baselines:
                methods['centerline'] = CenterlineFollower(env)
            if 'expert' in args.baselines:
                methods['expert'] = ScriptedExpert(env)
            results = {}
            for name, method in methods.items():
                t0 = time.monotonic()
                reuse = mode == 'static' and name != 'expert'   # the expert is seeded
                results[name] = run_trials(env, method, args.trials, args.seed, reuse)
                s = summarize(results[name])
                print(f"{mode} {name}: success {100 * s['success_rate']:.0f}% "
                      f"({time.monotonic() - t0:.0f} s)", flush=True)
            all_results[mode] = results
        notes = (f'Anatomy `{args.anatomy}`, {args.trials} trials per method, epsilon 10 mm, '
                 f'seed {args.seed}. Trial k: start k % 3, target (k // 3) % 5. In static mode a '
                 'deterministic method gives the same outcome for a repeated start x target '
                 'pair, so each pair is simulated once; the seeded expert runs every trial.')
        path = write_report(all_results, args.out, notes)
    except (LearningError, ValueError) as exc:
        print(f'evaluate: error: {exc}', file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == '__main__':
    sys.exit(main())
