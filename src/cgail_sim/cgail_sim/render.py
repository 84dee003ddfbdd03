"""Render an anatomy to PNG: vessel, centrelines, targets, starts, rollouts, heartbeat phases.

Command line (``cgail render``)::

    cgail render --anatomy default --out docs/img/anatomy_default.png
    cgail render --anatomy elongated --rollout tip_points.npy --phases 4 --out /tmp/a.png
    cgail render --anatomy runs/patients/p07          # a prepared anatomy: anatomy_p07.png
    cgail render --population 12 --seed 0 --out docs/img/population_grid.png

Two views side by side: anterior (coronal; viewer looking at the patient's front, the
patient's left on the right of the image) and left-lateral (viewer at the patient's left,
anterior on the left of the image). The wall is drawn semi-transparent with Lambert shading;
caps (non-wall faces) are grey. Targets and start configurations come from
``cgail_sim.scenarios`` when it is importable, otherwise only the ostia are marked.
With ``--phases N`` (needs ``cgail_sim.wall.DeformableWall``) the aortic root is
overlaid as wireframes at N phases of one heartbeat. ``--population N`` draws a grid of the
population samples ``--seed`` .. ``--seed + N - 1`` (:mod:`cgail_sim.population`), each
built and validated, in the anterior view, labelled with its seed, arch type, root tilt and age.
"""

from __future__ import annotations

import argparse
from collections.abc import Mapping, Sequence
import importlib
from pathlib import Path
import sys
from typing import Any

import numpy as np

from cgail_sim.anatomy import Anatomy, ANATOMY_NAMES, AnatomyError
from cgail_sim.anatomy_spec import resolve_anatomy
from cgail_sim.centerline import Centerline, compute_centerlines
from cgail_sim.cli_help import tool_parser

__all__ = ["VIEWS", "heartbeat_phases", "main", "render_anatomy", "render_population_grid"]

VIEWS: dict[str, tuple[float, float]] = {
    "anterior": (8.0, -90.0),
    "left-lateral": (8.0, 0.0),
    "root": (15.0, -60.0),
}
"""(elevation, azimuth) in degrees of the matplotlib camera for each named view (LPS frame).
"root" is a close-up of the aortic root (sinuses, coronary ostia) from anterior-left."""

_BRANCH_COLOURS = {"left": "#1f5fd6", "right": "#1a9e3a"}


def _shaded_colours(vertices: np.ndarray, faces: np.ndarray, base: tuple[float, float, float],
                    alpha: float, light: np.ndarray) -> np.ndarray:
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    lam = np.abs(n @ light)  # two-sided: the inside of the far wall is lit as well
    shade = 0.35 + 0.65 * lam
    rgba = np.empty((len(faces), 4))
    rgba[:, :3] = np.clip(np.outer(shade, base), 0.0, 1.0)
    rgba[:, 3] = alpha
    return rgba


def heartbeat_phases(anatomy: Anatomy, n_phases: int, dt: float = 0.005) -> list[np.ndarray]:
    """Wall vertices at ``n_phases`` evenly spaced phases of one heartbeat (no catheter).

    Raises:
        ImportError: ``cgail_sim.wall.DeformableWall`` is not available.
        ValueError: ``n_phases`` < 1.
    """
    if n_phases < 1:
        raise ValueError(f"n_phases must be >= 1, found {n_phases}")
    wall_mod = importlib.import_module("cgail_sim.wall")
    wall = wall_mod.DeformableWall(anatomy)
    period = float(wall.heartbeat.config.period)
    wall.reset()
    times = [k * period / n_phases for k in range(n_phases)]
    out: list[np.ndarray] = []
    t = 0.0
    empty = np.zeros((0, 3))
    for target in times:
        while t < target - 1e-9:
            step = min(dt, target - t)
            t += step
            wall.step(t, step, empty, 0.001)
        out.append(np.array(wall.vertices, dtype=float))
    return out


def _scenarios(anatomy: Anatomy,
               centerlines: dict[str, Centerline]) -> tuple[np.ndarray, np.ndarray] | None:
    """(targets (T,3), starts (S,3)) from cgail_sim.scenarios, or None."""
    try:
        scen = importlib.import_module("cgail_sim.scenarios")
        s = scen.build_scenarios(anatomy, centerlines)
    except (ImportError, AttributeError, ValueError) as err:
        print(f"cgail render: no scenarios drawn ({err})", file=sys.stderr)
        return None
    targets = np.array([t.position for t in s.targets], dtype=float).reshape(-1, 3)
    starts = np.array([q.position for q in s.starts], dtype=float).reshape(-1, 3)
    return targets, starts


def render_anatomy(anatomy: Anatomy, out: str | Path, *,
                   centerlines: dict[str, Centerline] | None = None,
                   rollout: np.ndarray | None = None, phases: Sequence[np.ndarray] = (),
                   scenarios: bool = True,
                   views: Sequence[str] = ("anterior", "left-lateral", "root"),
                   dpi: int = 110, title: str | None = None,
                   markers: Mapping[str, np.ndarray] | None = None,
                   rollouts: Sequence[tuple[str, np.ndarray, np.ndarray | None]] = ()) -> Path:
    """Draw the anatomy and overlays to a PNG.

    Args:
        anatomy: the vessel.
        out: PNG path (parent folders are created).
        centerlines: per-branch centrelines to draw (None: none).
        rollout: (T, 3) catheter tip points, m, drawn as a path.
        phases: wall vertex arrays (N, 3) at heartbeat phases, drawn as root wireframes.
        scenarios: draw targets and starts from ``cgail_sim.scenarios`` if available.
        views: names from :data:`VIEWS`.
        dpi: output resolution.
        title: figure title (default: the anatomy name).
        markers: further labelled points (m) to mark, e.g. ``{"annulus centre": p}``.
        rollouts: further labelled tip paths ``(label, (T, 3) points in m, target (3,) m or
            None)``, each in a colour of its own: its last point (where the episode ended)
            marked with a cross, its target with a star.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Line3DCollection, Poly3DCollection

    for v in views:
        if v not in VIEWS:
            raise ValueError(f"views must be from {sorted(VIEWS)}, found {v!r}")
    mm = 1e3
    verts = np.asarray(anatomy.vertices) * mm
    faces = np.asarray(anatomy.faces)
    wall = np.asarray(anatomy.wall_face_mask)
    scen = _scenarios(anatomy, centerlines) if (scenarios and centerlines) else None
    fig = plt.figure(figsize=(4.6 * len(views), 5.6))
    lo = verts.min(axis=0)
    hi = verts.max(axis=0)
    centre = 0.5 * (lo + hi)
    half = 0.5 * float((hi - lo).max()) * 0.85
    for k, view in enumerate(views):
        elev, azim = VIEWS[view]
        ax = fig.add_subplot(1, len(views), k + 1, projection="3d")
        e, a = np.radians(elev), np.radians(azim)
        cam = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        light = cam + np.array([0.0, 0.0, 0.8])
        light /= np.linalg.norm(light)
        c_view, h_view = centre, half
        if view == "root":
            c_view = (anatomy.annulus_center + 0.012 * anatomy.root_axis) * mm
            h_view = 24.0
        alpha = 0.45 if view == "root" else 0.30
        show = np.ones(len(faces), dtype=bool)
        if view == "root":
            near = np.linalg.norm(
                verts - (anatomy.annulus_center + 0.012 * anatomy.root_axis) * mm, axis=1) < 30
            show = near[faces].all(axis=1)
        wall_col = _shaded_colours(verts, faces[wall & show], (0.86, 0.30, 0.27), alpha, light)
        poly = Poly3DCollection(verts[faces[wall & show]], facecolors=wall_col,
                                edgecolors=(0.5, 0.1, 0.1, 0.12) if view == "root" else "none",
                                linewidths=0.2)
        ax.add_collection3d(poly)
        if (~wall & show).any():
            cap = Poly3DCollection(verts[faces[~wall & show]], facecolors=(0.55, 0.55, 0.55, 0.55),
                                   edgecolors="none")
            ax.add_collection3d(cap)
        for p_idx, pv in enumerate(phases):
            pv = np.asarray(pv) * mm
            root = np.linalg.norm(pv - anatomy.annulus_center * mm, axis=1) < 35.0
            f_root = faces[wall & root[faces].all(axis=1)]
            edges = np.concatenate([f_root[:, [0, 1]], f_root[:, [1, 2]]])
            colour = plt.get_cmap("viridis")(p_idx / max(1, len(phases) - 1))
            ax.add_collection3d(Line3DCollection(pv[edges], colors=[colour], linewidths=0.3,
                                                 alpha=0.6))
        def clip(pts: np.ndarray, view: str = view, c_view: np.ndarray = c_view,
                 h_view: float = h_view) -> np.ndarray:
            """Hide overlay points outside the close-up box of the root view."""
            if view != "root":
                return pts
            out = np.array(pts, dtype=float, copy=True)
            out[np.abs(out - c_view).max(axis=1) > h_view] = np.nan
            return out

        if centerlines:
            for branch, cl in centerlines.items():
                p = clip(cl.points * mm)
                ax.plot(p[:, 0], p[:, 1], p[:, 2], color=_BRANCH_COLOURS.get(branch, "k"),
                        lw=2.0, label=f"centreline {branch}")
        for branch, o in anatomy.ostia.items():
            o = o * mm
            ax.scatter([o[0]], [o[1]], [o[2]], s=40, marker="o",
                       color=_BRANCH_COLOURS.get(branch, "k"), edgecolors="k",
                       label=f"{branch} ostium", depthshade=False)
        if scen is not None:
            targets, starts = scen
            tg = clip(targets * mm)
            st = clip(starts * mm)
            ax.scatter(tg[:, 0], tg[:, 1], tg[:, 2], s=70, marker="*", color="gold",
                       edgecolors="k", label="targets", depthshade=False)
            ax.scatter(st[:, 0], st[:, 1], st[:, 2], s=40, marker="^", color="k",
                       label="starts", depthshade=False)
        else:
            s = clip(anatomy.start_point[None] * mm)[0]
            ax.scatter([s[0]], [s[1]], [s[2]], s=40, marker="^", color="k", label="start",
                       depthshade=False)
        for m_idx, (label, point) in enumerate((markers or {}).items()):
            q = clip(np.asarray(point, dtype=float).reshape(1, 3) * mm)[0]
            ax.scatter([q[0]], [q[1]], [q[2]], s=55, marker="X",
                       color=("#ff7f0e", "#17becf", "#8c564b", "#7f7f7f")[m_idx % 4],
                       edgecolors="k", label=label, depthshade=False)
        if rollout is not None and len(rollout):
            r = clip(np.asarray(rollout, dtype=float).reshape(-1, 3) * mm)
            ax.plot(r[:, 0], r[:, 1], r[:, 2], color="m", lw=1.6, label="catheter tip")
        for r_idx, (label, path, goal) in enumerate(rollouts):
            r = clip(np.asarray(path, dtype=float).reshape(-1, 3) * mm)
            if not len(r):
                continue
            colour = plt.get_cmap("tab10")(r_idx % 10)
            ax.plot(r[:, 0], r[:, 1], r[:, 2], color=colour, lw=1.6, label=label)
            ax.scatter([r[-1, 0]], [r[-1, 1]], [r[-1, 2]], s=60, marker="X", color=colour,
                       edgecolors="k", depthshade=False)
            if goal is not None:
                g = clip(np.asarray(goal, dtype=float).reshape(1, 3) * mm)[0]
                ax.scatter([g[0]], [g[1]], [g[2]], s=90, marker="*", color=colour,
                           edgecolors="k", depthshade=False)
        ax.set_xlim(c_view[0] - h_view, c_view[0] + h_view)
        ax.set_ylim(c_view[1] - h_view, c_view[1] + h_view)
        ax.set_zlim(c_view[2] - h_view, c_view[2] + h_view)
        ax.set_box_aspect((1, 1, 1), zoom=1.25)
        ax.view_init(elev=elev, azim=azim)
        ax.set_xlabel("x left (mm)", fontsize=7)
        ax.set_ylabel("y posterior (mm)", fontsize=7)
        ax.set_zlabel("z cranial (mm)", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.set_title(view, fontsize=9)
        if k == 0:
            ax.legend(loc="lower left", fontsize=6, framealpha=0.7)
    fig.suptitle(title or f"anatomy '{anatomy.name}': {len(verts)} vertices, "
                 f"{int(wall.sum())} wall faces", fontsize=10)
    return _save(fig, out, dpi)


def _save(fig: Any, out: str | Path, dpi: int) -> Path:
    """Lay out ``fig``, write it to ``out`` (parents created) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    out_path = Path(out)
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=dpi)
    plt.close(fig)
    return out_path


def render_population_grid(seeds: Sequence[int], out: str | Path, *, cols: int = 4,
                           view: str = "anterior", dpi: int = 90) -> Path:
    """Draw population samples (:func:`cgail_sim.population.sample_population`) in a
    grid, one anatomy per panel on a common scale, labelled with seed, arch type, root tilt
    and age.

    Args:
        seeds: the population seeds (each built and validated; a few seconds each when not
            cached).
        out: PNG path (parent folders are created).
        cols: panels per row.
        view: a name from :data:`VIEWS` ("root" is not a whole-aorta view and is refused).
        dpi: output resolution.

    Returns:
        The written path.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from cgail_sim.population import sample_population

    if view not in VIEWS or view == "root":
        raise ValueError(f"view must be one of {sorted(set(VIEWS) - {'root'})}, found {view!r}")
    if not seeds:
        raise ValueError("seeds must name at least one population sample, found none")
    if cols < 1:
        raise ValueError(f"cols must be >= 1, found {cols}")
    samples = [sample_population(s) for s in seeds]
    mm = 1e3
    half = 0.5 * max(float(np.ptp(np.asarray(s.anatomy.vertices) * mm, axis=0).max())
                     for s in samples) * 0.8
    rows = -(-len(samples) // cols)
    fig = plt.figure(figsize=(3.3 * cols, 3.6 * rows))
    elev, azim = VIEWS[view]
    e, a = np.radians(elev), np.radians(azim)
    cam = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    light = cam + np.array([0.0, 0.0, 0.8])
    light /= np.linalg.norm(light)
    for k, smp in enumerate(samples):
        anatomy, d = smp.anatomy, smp.draw
        verts = np.asarray(anatomy.vertices) * mm
        faces = np.asarray(anatomy.faces)
        wall = np.asarray(anatomy.wall_face_mask)
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        ax.add_collection3d(Poly3DCollection(
            verts[faces[wall]], edgecolors="none",
            facecolors=_shaded_colours(verts, faces[wall], (0.86, 0.30, 0.27), 0.45, light)))
        ax.add_collection3d(Poly3DCollection(verts[faces[~wall]],
                                             facecolors=(0.55, 0.55, 0.55, 0.6),
                                             edgecolors="none"))
        for branch, o in anatomy.ostia.items():
            ax.scatter(*(o * mm), s=18, color=_BRANCH_COLOURS.get(branch, "k"), edgecolors="k",
                       depthshade=False)
        centre = 0.5 * (verts.min(axis=0) + verts.max(axis=0))
        for lim, c in zip((ax.set_xlim, ax.set_ylim, ax.set_zlim), centre, strict=True):
            lim(c - half, c + half)
        ax.set_box_aspect((1, 1, 1), zoom=1.2)
        ax.view_init(elev=elev, azim=azim)
        ax.set_axis_off()
        ax.set_title(f"seed {d.seed}: type {'I' * d.arch_type}, "
                     f"tilt {d.root_tilt_deg:.0f} deg\nage {d.age:.0f}, {d.sex}, "
                     f"draws {d.draws}", fontsize=8)
    fig.suptitle(f"anatomy population, seeds {seeds[0]}-{seeds[-1]} ({view} view; ostia: "
                 "blue left, green right; same scale)", fontsize=10)
    return _save(fig, out, dpi)


def _default_out(name: str) -> str:
    """``runs/render/<name>``, its directory made: every tool writes under ``runs/``."""
    Path("runs", "render").mkdir(parents=True, exist_ok=True)
    return str(Path("runs", "render", name))


def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail render``."""
    ap = tool_parser("render", __doc__, details=True)
    ap.add_argument("--anatomy", default="default",
                    help=f"built-in anatomy {list(ANATOMY_NAMES)}, a prepared anatomy directory "
                         "or a mesh file (mm) with a <stem>.yaml landmark sidecar")
    ap.add_argument("--out", default=None,
                    help="PNG path (default runs/render/anatomy_<label>.png: the name, the "
                         "directory name or the mesh stem; with --population "
                         "runs/render/population_grid.png)")
    ap.add_argument("--rollout", default=None, help=".npy file of (T, 3) tip points in m")
    ap.add_argument("--phases", type=int, default=0,
                    help="overlay the root at N heartbeat phases (needs sim.wall)")
    ap.add_argument("--no-centerlines", action="store_true", help="skip the centrelines")
    ap.add_argument("--no-scenarios", action="store_true", help="skip targets and starts")
    ap.add_argument("--dpi", type=int, default=110, help="resolution of the PNG, dots per inch")
    ap.add_argument("--population", type=int, default=0, metavar="N",
                    help="draw a grid of N population samples (sim.population) instead of "
                         "--anatomy (default out: population_grid.png)")
    ap.add_argument("--seed", type=int, default=0,
                    help="first population seed of the grid (--population)")
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail render``; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        if args.population:
            if args.population < 0 or args.seed < 0:
                raise ValueError(f"population and seed must be >= 0, found {args.population} "
                                 f"and {args.seed}")
            seeds = list(range(args.seed, args.seed + args.population))
            path = render_population_grid(seeds, args.out or _default_out("population_grid.png"),
                                          dpi=args.dpi)
            print(path)
            return 0
        anatomy = resolve_anatomy(args.anatomy)
        centerlines = None if args.no_centerlines else compute_centerlines(anatomy)
        rollout = None
        if args.rollout:
            rollout = np.load(args.rollout)
            if rollout.ndim != 2 or rollout.shape[1] != 3:
                raise ValueError(f"rollout must be a (T, 3) array, found shape {rollout.shape}")
        phases: list[Any] = []
        if args.phases:
            try:
                phases = heartbeat_phases(anatomy, args.phases)
            except ImportError as err:
                print(f"cgail render: --phases needs sim.wall.DeformableWall ({err})",
                      file=sys.stderr)
                return 2
        if args.phases < 0:
            raise ValueError(f"phases must be >= 0, found {args.phases}")
        out = args.out or _default_out(f"anatomy_{anatomy.name}.png")
        path = render_anatomy(anatomy, out, centerlines=centerlines, rollout=rollout,
                              phases=phases, scenarios=not args.no_scenarios, dpi=args.dpi)
    except (AnatomyError, ValueError, OSError) as err:
        print(f"cgail render: error: {err}", file=sys.stderr)
        return 2
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
