"""Per-step cost of the simulator's wall: PBD step, raycasts and tip contact.

Prints milliseconds per call (median of repeated calls after a warm-up that also compiles the
numba kernels) on the default anatomy, as CPU time of the calling thread and as wall-clock time
(on a shared, loaded machine the CPU time is the cost; the wall time includes waiting):

* PBD step (10 iterations) with the heartbeat, without and with a catheter body pressing the
  descending-aorta wall by 1 mm along 60 mm;
* a 16-ray raycast against the static wall and against the deforming wall (refit included);
* ``tip_contact`` on the deformable wall (closest point, pseudo-normal, Newton force).

Run: ``scripts/ws python bench/bench_wall.py [--anatomy default] [--repeats 200]``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
import time

import numpy as np

from cgail_planner.sim.anatomy import build_anatomy
from cgail_planner.sim.wall import DeformableWall, StaticWall

RADIUS = 0.0035
DT = 0.1


def _median_ms(fn: Callable[[], object], repeats: int) -> tuple[float, float]:
    """(median CPU ms of this thread, median wall-clock ms) per call."""
    cpu = []
    wall = []
    for _ in range(repeats):
        w0 = time.perf_counter()
        c0 = time.thread_time()
        fn()
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - w0)
    return 1e3 * float(np.median(cpu)), 1e3 * float(np.median(wall))


def _rays(n: int) -> np.ndarray:
    """n unit directions on a cone of 45 deg around +z plus the axis (a typical tip fan)."""
    ang = np.linspace(0.0, 2.0 * np.pi, n - 1, endpoint=False)
    d = np.stack([np.cos(ang), np.sin(ang), np.ones_like(ang)], axis=1)
    d = np.vstack([d, [0.0, 0.0, 1.0]])
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--anatomy", default="default")
    parser.add_argument("--repeats", type=int, default=200)
    args = parser.parse_args()
    anatomy = build_anatomy(args.anatomy)
    static = StaticWall(anatomy)
    wall = DeformableWall(anatomy)
    start = anatomy.start_point
    axis = anatomy.start_direction / np.linalg.norm(anatomy.start_direction)
    side = np.cross(axis, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    gap = float(static.raycast(start[None], side[None], 0.1)[0])
    s = np.arange(0.0, 0.0601, 0.005)
    free_body = start + s[:, None] * axis
    pressing = free_body + (gap - RADIUS + 0.001) * side  # 1 mm into the rest wall
    none = np.zeros((0, 3))
    origins = np.repeat(free_body[-1][None], 16, axis=0)
    dirs = _rays(16)
    # Align the ray fan with the body direction.
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, axis)
    c = float(z @ axis)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    rot = np.eye(3) + vx + vx @ vx / (1.0 + c)
    dirs = dirs @ rot.T

    counter = {"k": 0}

    def step(body: np.ndarray) -> Callable[[], None]:
        def run() -> None:
            counter["k"] += 1
            wall.step(counter["k"] * DT, DT, body, RADIUS)
        return run

    def deforming_raycast() -> None:
        wall._dirty = True  # force the refit a real step would cause
        wall.raycast(origins, dirs, 0.04)

    # Warm-up (numba compilation / cache load).
    for body in (none, pressing):
        for _ in range(3):
            step(body)()
    static.raycast(origins, dirs, 0.04)
    deforming_raycast()
    wall.tip_contact(pressing[-1], RADIUS, DT)

    n = anatomy.vertices.shape[0]
    print(f"anatomy {anatomy.name!r}: {n} vertices, {int(anatomy.wall_face_mask.sum())} wall "
          f"faces; PBD {wall.pbd_config.iterations} iterations x {wall.pbd_config.substeps} "
          f"substep(s), dt = {DT} s")
    rows = [
        ("PBD step, heartbeat, no catheter", _median_ms(step(none), args.repeats)),
        ("PBD step, heartbeat, catheter free in lumen",
         _median_ms(step(free_body), args.repeats)),
        ("PBD step, heartbeat, catheter pressing 1 mm",
         _median_ms(step(pressing), args.repeats)),
        ("raycast 16 rays, static wall", _median_ms(
            lambda: static.raycast(origins, dirs, 0.04), args.repeats)),
        ("raycast 16 rays, deforming wall (refit + cast)",
         _median_ms(deforming_raycast, args.repeats)),
    ]

    def contact() -> None:
        wall._forces = None  # recompute the elastic forces as after a real step
        wall.tip_contact(pressing[-1], RADIUS, DT)

    rows.append(("tip_contact, deformable wall (after a pressing step)",
                 _median_ms(contact, args.repeats)))
    rows.append(("tip_contact, static wall",
                 _median_ms(lambda: static.tip_contact(pressing[-1], RADIUS, DT),
                            args.repeats)))
    print(f"{'':<55s} {'CPU ms':>8s} {'wall ms':>8s}")
    for name, (cpu_ms, wall_ms) in rows:
        print(f"{name:<55s} {cpu_ms:8.3f} {wall_ms:8.3f}")
    c = wall.tip_contact(pressing[-1], RADIUS, DT)
    print(f"pressing contact: force {c.force:.3f} N, penetration {c.penetration * 1e3:.3f} mm, "
          f"in_contact {c.in_contact}")


if __name__ == "__main__":
    main()
