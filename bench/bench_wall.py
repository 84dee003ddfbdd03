"""Per-step cost of the simulator's wall: PBD step, raycasts and tip contact.

Prints milliseconds per call on a built-in anatomy, after a warm-up that also loads or compiles
the numba kernels: the median CPU time of the calling thread (the cost; on a shared, loaded
machine the wall-clock time also counts waiting for a core), the fastest CPU time, and the
median wall-clock time.

* PBD step with the heartbeat (one numba call, BVH refit to the new shape included): no
  catheter, a catheter free in the lumen (contact broad phase only), and a catheter pressing the
  descending-aorta wall by 1 mm along 60 mm; default solver (VBD, 10 sweeps), VBD with 8 sweeps,
  VBD with 5 Chebyshev-accelerated sweeps (the dynamic env's default,
  ``cgail_sim.env.DYNAMIC_PBD_CONFIG``), VBD with 5 plain sweeps, and XPBD (10
  iterations) for comparison;
* a 16-ray raycast against the static wall and against the deforming wall (with a refit, the
  cost the step now pays);
* ``tip_contact`` on the deformable wall (closest point, pseudo-normal, Newton force) and on the
  static wall.

With ``--accuracy`` it also prints how converged each VBD setting is: four beats (34 steps, no
catheter) against a 60-sweep solve, the rms and 99th-percentile particle position error and the
range of the ostium-target heartbeat amplitude (beats 3-4) relative to the reference: the
evidence behind ``DYNAMIC_PBD_CONFIG``.

With ``--contact`` it also runs full-length contact trials on the dynamic env
(:func:`cgail_sim.contact_trial.run_contact_trials`: the catheter riding the wall, tip
aimed ``--depth`` mm beyond it, ``--steps`` steps, six sides) and prints per trial the largest
particle displacement and the body's indentation into the rest wall at that moment; any
anatomy the env accepts (a built-in name or a prepared patient directory).

Run: ``scripts/ws python bench/bench_wall.py [--anatomy default] [--repeats 200] [--accuracy]
[--contact [--depth 1] [--steps 2000] [--trials 6] [--contact-only]]``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import time

import numpy as np

from cgail_sim.anatomy import build_anatomy
from cgail_sim.env import DYNAMIC_PBD_CONFIG
from cgail_sim.pbd import PBDConfig
from cgail_sim.wall import DeformableWall, StaticWall
from cgail_sim.worlds import load_world

RADIUS = 0.0035
DT = 0.1


def _timing(fn: Callable[[], object], repeats: int) -> tuple[float, float, float]:
    """(median CPU ms, fastest CPU ms, median wall-clock ms) per call."""
    cpu = []
    wall = []
    for _ in range(repeats):
        w0 = time.perf_counter()
        c0 = time.thread_time()
        fn()
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - w0)
    return (1e3 * float(np.median(cpu)), 1e3 * float(np.min(cpu)),
            1e3 * float(np.median(wall)))


def _ray_fan(axis: np.ndarray, n: int = 16) -> np.ndarray:
    """n unit directions: the axis and a 45-degree cone around it (a typical tip fan)."""
    e0 = np.cross(axis, [1.0, 0.0, 0.0])
    if np.linalg.norm(e0) < 1e-6:
        e0 = np.cross(axis, [0.0, 1.0, 0.0])
    e0 /= np.linalg.norm(e0)
    e1 = np.cross(axis, e0)
    ang = np.linspace(0.0, 2.0 * np.pi, n - 1, endpoint=False)
    d = axis + np.cos(ang)[:, None] * e0 + np.sin(ang)[:, None] * e1
    d = np.vstack([d, axis])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def accuracy(anatomy_name: str) -> None:
    """Print the convergence of the VBD settings against a 60-sweep solve (see module doc)."""
    world = load_world(anatomy_name)
    anatomy = world.anatomy
    targets = np.array([t.vertex for t in world.scenarios.targets])
    none = np.zeros((0, 3))

    def run(cfg: PBDConfig) -> np.ndarray:
        wall = DeformableWall(anatomy, cfg)
        out = []
        for k in range(1, 35):  # four beats at 70 bpm
            wall.step(k * DT, DT, none, RADIUS)
            out.append(wall.vertices.copy())
        return np.array(out)

    ref = run(PBDConfig(iterations=60))
    rest = anatomy.vertices[targets]
    amp_ref = np.linalg.norm(ref[17:, targets] - rest, axis=2).max(axis=0)
    print(f"convergence on {anatomy_name!r}, 34 steps (4 beats), against 60 plain sweeps:")
    print(f"  {'':34s} {'rms mm':>7s} {'p99 mm':>7s}  ostium amplitude vs reference")
    for label, cfg in (("VBD 20 sweeps", PBDConfig(iterations=20)),
                       ("VBD 10 sweeps (default)", PBDConfig()),
                       ("VBD 8 sweeps", PBDConfig(iterations=8)),
                       ("VBD 5 Chebyshev sweeps (env)", DYNAMIC_PBD_CONFIG),
                       ("VBD 5 sweeps", PBDConfig(iterations=5))):
        x = run(cfg)
        err = np.linalg.norm(x - ref, axis=2)
        amp = np.linalg.norm(x[17:, targets] - rest, axis=2).max(axis=0) / amp_ref - 1.0
        print(f"  {label:34s} {1e3 * np.sqrt(np.mean(err**2)):7.3f} "
              f"{1e3 * np.percentile(err, 99):7.3f}  {100 * amp.min():+6.1f} % .. "
              f"{100 * amp.max():+6.1f} %")


def contact(anatomy: str, trials: int, steps: int, depth_mm: float) -> None:
    """Print the full-length contact trials (see module doc)."""
    from cgail_sim.contact_trial import run_contact_trials

    t0 = time.perf_counter()
    out = run_contact_trials(anatomy, trials=trials, steps=steps, depth=depth_mm * 1e-3)
    print(f"contact trials on {anatomy!r}: tip aimed {depth_mm:g} mm beyond the wall, "
          f"{steps} steps ({time.perf_counter() - t0:.0f} s)")
    print(f"  {'start':>5s} {'target':>6s} {'side':>4s} {'end':>16s} {'steps':>5s} "
          f"{'contact':>7s} {'max disp mm':>11s} {'indentation mm':>14s}")
    for t in out:
        print(f"  {t.start:5d} {t.target:6d} {t.direction:4d} {t.end:>16s} {t.steps:5d} "
              f"{t.contact_steps:7d} {t.max_displacement_mm:11.1f} {t.indentation_mm:14.1f}")
        if t.fault:
            print(f"    {t.fault}")
    print(f"  largest displacement {max(t.max_displacement_mm for t in out):.1f} mm, "
          f"faults {sum(t.end == 'simulation fault' for t in out)} / {len(out)}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--anatomy", default="default")
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--accuracy", action="store_true",
                        help="also print the convergence of the VBD settings")
    parser.add_argument("--contact", action="store_true",
                        help="also run full-length contact trials on the dynamic env")
    parser.add_argument("--contact-only", action="store_true",
                        help="only the contact trials (no timings)")
    parser.add_argument("--depth", type=float, default=1.0,
                        help="contact trials: tip aim beyond the wall, mm")
    parser.add_argument("--steps", type=int, default=2000, help="contact trials: steps")
    parser.add_argument("--trials", type=int, default=6, help="contact trials: trials")
    args = parser.parse_args()
    if args.contact_only:
        contact(args.anatomy, args.trials, args.steps, args.depth)
        return
    anatomy = build_anatomy(args.anatomy)
    static = StaticWall(anatomy)
    axis = anatomy.start_direction / np.linalg.norm(anatomy.start_direction)
    side = np.cross(axis, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    start = anatomy.start_point
    gap = float(static.raycast(start[None], side[None], 0.1)[0])
    free_body = start + np.arange(0.0, 0.0601, 0.005)[:, None] * axis
    pressing = free_body + (gap - RADIUS + 0.001) * side  # 1 mm into the rest wall
    none = np.zeros((0, 3))
    origins = np.repeat(free_body[-1][None], 16, axis=0)
    dirs = _ray_fan(axis)

    print(f"anatomy {anatomy.name!r}: {anatomy.vertices.shape[0]} vertices, "
          f"{int(anatomy.wall_face_mask.sum())} wall faces; dt = {DT} s, 1 substep")
    print(f"{'':<58s} {'CPU med':>8s} {'CPU min':>8s} {'wall med':>8s}  (ms)")

    def report(name: str, t: tuple[float, float, float]) -> None:
        print(f"{name:<58s} {t[0]:8.3f} {t[1]:8.3f} {t[2]:8.3f}")

    default_wall = None
    for label, cfg in (("VBD 10 sweeps (default)", PBDConfig()),
                       ("VBD 8 sweeps", PBDConfig(iterations=8)),
                       ("VBD 5 Chebyshev sweeps (env)", DYNAMIC_PBD_CONFIG),
                       ("VBD 5 sweeps", PBDConfig(iterations=5)),
                       ("XPBD 10 iterations", PBDConfig(solver="xpbd"))):
        wall = DeformableWall(anatomy, cfg)
        counter = [0]

        def step(body: np.ndarray, wall: DeformableWall = wall,
                 counter: list[int] = counter) -> Callable[[], None]:
            def run() -> None:
                counter[0] += 1
                wall.step(counter[0] * DT, DT, body, RADIUS)
            return run

        for body in (none, free_body, pressing):
            for _ in range(3):  # warm-up / numba cache load
                step(body)()
        for body_name, body in (("no catheter", none), ("catheter free", free_body),
                                ("catheter pressing 1 mm", pressing)):
            report(f"step, {label}, {body_name}", _timing(step(body), args.repeats))
        if default_wall is None:
            default_wall = wall

    assert default_wall is not None
    wall = default_wall

    def deforming_raycast() -> None:
        wall._dirty = True  # the refit a real step causes
        wall.raycast(origins, dirs, 0.04)

    def deformable_contact() -> None:
        wall.tip_contact(pressing[-1], RADIUS, DT)  # (elastic forces evaluated every call)

    static.raycast(origins, dirs, 0.04)
    deforming_raycast()
    report("raycast 16 rays, static wall",
           _timing(lambda: static.raycast(origins, dirs, 0.04), args.repeats))
    report("raycast 16 rays, deforming wall (refit + cast)",
           _timing(deforming_raycast, args.repeats))
    report("tip_contact, deformable wall (after a pressing step)",
           _timing(deformable_contact, args.repeats))
    report("tip_contact, static wall",
           _timing(lambda: static.tip_contact(pressing[-1], RADIUS, DT), args.repeats))
    result = wall.tip_contact(pressing[-1], RADIUS, DT)
    print(f"pressing contact (VBD 10): force {result.force:.3f} N, penetration "
          f"{result.penetration * 1e3:.3f} mm, in_contact {result.in_contact}")
    if args.accuracy:
        accuracy(args.anatomy)
    if args.contact:
        contact(args.anatomy, args.trials, args.steps, args.depth)


if __name__ == "__main__":
    main()
