"""The gap between the real aortas and the synthetic population, descriptor by descriptor.

Measures every anatomy descriptor (:mod:`cgail_sim.descriptors`: root tilt, arch width and
height, length, tortuosity, curvature and lumen radii of the arch and of the descending aorta,
the supra-aortic branches' take-off positions and angles) on

* the real cases of ``data/anatomies/avt/`` (11 CTA segmentations, CC BY 4.0; see its README
  for the citation), each prepared with ``cgail prepare-anatomy --no-expert-check
  --no-wall-check`` (the checks do not change the mesh; a case the other checks refuse is
  measured on its ``lumen.rejected.stl``), and
* the population samples ``population-<seed>`` of the training seeds ``--first-seed`` ...
  (drawn and built as :func:`cgail_sim.population.sample_anatomy` builds them, without its
  validation run, which accepts the first draw of every seed it was run on; a draw the build
  refuses falls back to ``sample_population``),

and writes under ``--out`` (default ``runs/anatomy_gap``):

* ``<descriptor>.png``: the population's histogram, its 1st-99th percentile band, and each
  real case as a labelled point (red: outside the band);
* ``anatomy_gap.md``: the population's percentiles per descriptor, one table per real case
  (each descriptor, its value, the band, inside or not) and the summary of which real cases
  fall outside on which descriptors; ``descriptors.yaml``: every value (display units);
* ``real/<case>/``: the prepared cases, reused on the next run (``--reprepare`` redoes them);
  ``cache/``: each anatomy's descriptors, keyed by its content hash and the descriptor code.

    scripts/ws python bench/bench_anatomy_gap.py                        # 11 cases, 200 seeds
    scripts/ws python bench/bench_anatomy_gap.py --population 50 --cases D18 D11

A cold run builds each population mesh (~3 s) and measures each anatomy (~1.3 s); the meshes
are then in the disk cache (``~/.cache/cgail_planner``) and the descriptors in ``OUT/cache``.
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
import contextlib
import io
import json
import math
import os
from pathlib import Path
import re
import sys
import time
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_real_patients import find_cases  # noqa: E402  (a sibling bench script)

from cgail_sim import centerline, descriptors, disk_cache  # noqa: E402
from cgail_sim.anatomy import Anatomy, AnatomyError, load_anatomy_mesh  # noqa: E402
from cgail_sim.descriptors import DESCRIPTORS  # noqa: E402

LOW_PCT, HIGH_PCT = 1.0, 99.0
"""The population band a real value is compared with (percentiles)."""


# ------------------------------------------------------------------------------------------
# Measuring
# ------------------------------------------------------------------------------------------
def _cache_file(out: Path, anatomy: Anatomy) -> Path:
    key = disk_cache.cache_key(sources=(descriptors.__file__, centerline.__file__),
                               inputs=anatomy.content_hash, length=20)
    return out / "cache" / f"{key}.json"


def measure(anatomy: Anatomy, out: Path) -> dict[str, float]:
    """Every descriptor of ``anatomy`` in display units (NaN where not measurable), read from
    ``out/cache`` when this anatomy and this code measured it before."""
    path = _cache_file(out, anatomy)
    if path.is_file():
        data: dict[str, float] = json.loads(path.read_text())
        return data
    si = descriptors.anatomy_descriptors(anatomy).values()
    values = {d.key: float(si[d.key] * d.scale) for d in DESCRIPTORS}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(json.dumps(values))     # NaN is written as NaN, which json reads back
    tmp.replace(path)
    return values


def prepared_real(seg: Path, out: Path, reprepare: bool) -> tuple[Path | None, str]:
    """The prepared lumen of one case (``out/real/<case>``), preparing it when needed:
    ``(mesh, status)``; mesh None when ``prepare_anatomy`` refused the input."""
    from cgail_patient import PatientError
    from cgail_patient.prepare_cli import prepare_anatomy

    name = seg.parent.name
    folder = out / "real" / name
    usable = "prepared (the expert and wall checks skipped)"
    for mesh, status in ((folder / "lumen.stl", usable),
                         (folder / "lumen.rejected.stl", "refused by the geometry checks")):
        if mesh.is_file() and not reprepare:
            return mesh, status + ", reused"
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            result = prepare_anatomy([str(seg), "--out", str(folder), "--name", name,
                                      "--no-expert-check", "--no-wall-check"])
    except (PatientError, AnatomyError, OSError) as e:
        return None, f"input refused: {e}"
    if result.usable:
        return folder / "lumen.stl", usable
    why = "; ".join(f"{c.name}: {c.message}" for c in result.validation.errors)
    return folder / "lumen.rejected.stl", f"refused by the geometry checks ({why})"


def annulus_uncertainty_mm(folder: Path) -> float:
    """The annulus's uncertainty along the root axis that ``prepare_anatomy`` reported (mm; NaN
    when its report does not say)."""
    report = folder / "report.md"
    found = re.search(r"annulus uncertainty \+- ([0-9.]+) mm",
                      report.read_text() if report.is_file() else "")
    return float(found.group(1)) if found else math.nan


def real_case(seg: Path, out: Path, reprepare: bool) -> dict[str, Any]:
    """Prepare (or reuse) and measure one real case (runs in a worker when --jobs > 1)."""
    t0 = time.perf_counter()
    mesh, status = prepared_real(seg, out, reprepare)
    row: dict[str, Any] = {"name": seg.parent.name, "status": status,
                           "annulus_uncertainty_mm": annulus_uncertainty_mm(
                               out / "real" / seg.parent.name)}
    if mesh is not None:
        try:
            row["values"] = measure(load_anatomy_mesh(mesh, name=seg.parent.name), out)
        except AnatomyError as e:
            row["status"] += f"; not measurable: {e}"
    row["seconds"] = time.perf_counter() - t0
    return row


def population_case(seed: int, out: Path) -> dict[str, Any]:
    """Build (or load) and measure population sample ``seed``."""
    from cgail_sim import population
    from cgail_sim.anatomy import build_anatomy_from_params

    t0 = time.perf_counter()
    draw = population.population_draw(seed)
    try:
        anatomy = build_anatomy_from_params(draw.params, population.population_name(seed))
    except AnatomyError:
        anatomy = population.sample_population(seed, wall=False).anatomy
    row: dict[str, Any] = {"name": population.population_name(seed), "seed": seed,
                           "values": measure(anatomy, out)}
    row["seconds"] = time.perf_counter() - t0
    return row


# ------------------------------------------------------------------------------------------
# Comparing
# ------------------------------------------------------------------------------------------
def bands(population: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Per descriptor: n, the 1st / 50th / 99th percentiles, min and max of the population."""
    out: dict[str, dict[str, float]] = {}
    for d in DESCRIPTORS:
        v = np.array([p[d.key] for p in population], dtype=float)
        v = v[np.isfinite(v)]
        if len(v) == 0:
            out[d.key] = {"n": 0, "low": math.nan, "median": math.nan, "high": math.nan,
                          "min": math.nan, "max": math.nan}
            continue
        lo, med, hi = np.percentile(v, [LOW_PCT, 50.0, HIGH_PCT])
        out[d.key] = {"n": len(v), "low": float(lo), "median": float(med), "high": float(hi),
                      "min": float(v.min()), "max": float(v.max())}
    return out


def verdict(value: float, band: dict[str, float]) -> str:
    """'inside', 'below', 'above' or 'n/a' (no value or no population)."""
    if not math.isfinite(value) or band["n"] == 0:
        return "n/a"
    if value < band["low"]:
        return "below"
    if value > band["high"]:
        return "above"
    return "inside"


def _fmt(x: float, unit: str) -> str:
    if not math.isfinite(x):
        return "-"
    if unit == "-":
        if x == round(x):
            return f"{x:.0f}"
        return f"{x:.4f}" if abs(x) < 0.1 else f"{x:.2f}" if abs(x) < 10 else f"{x:.1f}"
    return f"{x:.1f}" if abs(x) < 100 else f"{x:.0f}"


def outside(real: list[dict[str, Any]], band: dict[str, dict[str, float]]
            ) -> dict[str, list[tuple[str, str, float]]]:
    """Per real case: (descriptor key, below/above, value) of each descriptor outside."""
    out: dict[str, list[tuple[str, str, float]]] = {}
    for r in real:
        vals = r.get("values", {})
        out[r["name"]] = [(d.key, v, vals[d.key]) for d in DESCRIPTORS
                          if (v := verdict(vals.get(d.key, math.nan), band[d.key]))
                          in ("below", "above")]
    return out


def markdown(real: list[dict[str, Any]], n_pop: int, seeds: str,
             band: dict[str, dict[str, float]]) -> str:
    """The report: population percentiles, one table per real case, the summary."""
    units = {d.key: d.unit for d in DESCRIPTORS}
    labels = {d.key: d.label for d in DESCRIPTORS}
    lines = ["# Real aortas against the synthetic population", "",
             f"Population: {n_pop} samples ({seeds}); real: {len(real)} AVT cases. A real value "
             f"is *outside* when it lies below the population's {LOW_PCT:g}st or above its "
             f"{HIGH_PCT:g}th percentile. Definitions: `cgail_sim.descriptors`.", "",
             "Read the real cases with two caveats. Without a left-ventricle label the annulus "
             "lies at the segmentation's lower end, uncertain along the root axis (each case "
             "says by how much), and the ascending length, the arch height and the take-off "
             "positions move with it. The descending length is where the lumen was cut "
             "(`prepare_anatomy` for a real case, the sampler's descending length for the "
             "population): extent, not anatomy.", "",
             "## Summary", ""]
    out = outside(real, band)
    for r in real:
        if "values" not in r:
            lines.append(f"- **{r['name']}**: not measured ({r['status']})")
            continue
        items = out[r["name"]]
        if not items:
            lines.append(f"- **{r['name']}**: inside on every descriptor")
            continue
        text = "; ".join(
            f"{labels[k]} {_fmt(v, units[k])} {units[k]} ({side}: "
            f"{_fmt(band[k]['low'], units[k])}-{_fmt(band[k]['high'], units[k])})"
            for k, side, v in items)
        lines.append(f"- **{r['name']}** ({len(items)} outside): {text}")
    lines += ["", "By descriptor (real cases outside the band):", ""]
    for d in DESCRIPTORS:
        names = [f"{r['name']} ({side})" for r in real for k, side, _ in out.get(r["name"], [])
                 if k == d.key]
        lines.append(f"- {d.label}: {', '.join(names) if names else 'none'}")
    lines += ["", "## Population", "",
              "| descriptor | unit | n | p1 | median | p99 | min | max |",
              "|---|---|---|---|---|---|---|---|"]
    for d in DESCRIPTORS:
        b = band[d.key]
        lines.append(f"| {d.label} | {d.unit} | {b['n']:.0f} | {_fmt(b['low'], d.unit)} | "
                     f"{_fmt(b['median'], d.unit)} | {_fmt(b['high'], d.unit)} | "
                     f"{_fmt(b['min'], d.unit)} | {_fmt(b['max'], d.unit)} |")
    lines += ["", "## Real cases", ""]
    for r in real:
        lines += [f"### {r['name']}", "", f"{r['status'][0].upper()}{r['status'][1:]}."]
        unc = r.get("annulus_uncertainty_mm", math.nan)
        if math.isfinite(unc):
            lines.append(f"Annulus +- {unc:.0f} mm along the root axis (no left-ventricle "
                         "label): the ascending length, the arch height and the take-off "
                         "positions carry that uncertainty.")
        lines.append("")
        if "values" not in r:
            continue
        lines += ["| descriptor | value | population p1-p99 | |", "|---|---|---|---|"]
        for d in DESCRIPTORS:
            v = r["values"][d.key]
            b = band[d.key]
            mark = {"inside": "inside", "below": "**below**", "above": "**above**",
                    "n/a": "n/a"}[verdict(v, b)]
            lines.append(f"| {d.label} | {_fmt(v, d.unit)} {d.unit} | "
                         f"{_fmt(b['low'], d.unit)}-{_fmt(b['high'], d.unit)} | {mark} |")
        lines.append("")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------------------
# Plotting
# ------------------------------------------------------------------------------------------
def plot(key: str, population: list[dict[str, float]], real: list[dict[str, Any]],
         band: dict[str, float], path: Path, n_pop: int) -> None:
    """One descriptor: population histogram over a strip of the real cases, one row each."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = next(x for x in DESCRIPTORS if x.key == key)
    pop = np.array([p[key] for p in population], dtype=float)
    pop = pop[np.isfinite(pop)]
    rows = [(r["name"], float(r["values"][key])) for r in real if "values" in r]
    shown = [(n, v) for n, v in rows if math.isfinite(v)]
    missing = [n for n, v in rows if not math.isfinite(v)]
    everything = np.concatenate([pop, [v for _, v in shown]])
    lo, hi = (float(everything.min()), float(everything.max())) if len(everything) else (0, 1)
    pad = 0.06 * (hi - lo) if hi > lo else max(abs(lo) * 0.1, 1.0)
    fig, (ax_pop, ax_real) = plt.subplots(
        2, 1, sharex=True, figsize=(8.0, 5.6),
        gridspec_kw={"height_ratios": [1.0, 1.25], "hspace": 0.08})
    if len(pop):
        if np.ptp(pop) > 0:
            ax_pop.hist(pop, bins=min(40, max(10, len(pop) // 5)), color="0.55",
                        edgecolor="white", linewidth=0.5)
        else:
            ax_pop.bar([pop[0]], [len(pop)], width=2 * pad / 3, color="0.55")
    for ax in (ax_pop, ax_real):
        if band["n"]:
            ax.axvspan(band["low"], band["high"], color="tab:blue", alpha=0.12, lw=0)
            for x in (band["low"], band["high"]):
                ax.axvline(x, color="tab:blue", lw=1.0, ls="--")
    if band["n"]:
        ax_pop.axvline(band["median"], color="tab:blue", lw=1.2)
    ax_pop.set_ylabel("population samples")
    ax_pop.set_title(f"{d.label} ({d.unit})", fontsize=12, loc="left")
    ax_pop.set_title(f"population: {len(pop)} of {n_pop} measured\nband p{LOW_PCT:g}-"
                     f"p{HIGH_PCT:g}, line: median", fontsize=8, color="0.3", loc="right")
    shown.sort(key=lambda nv: nv[1])
    for i, (_, v) in enumerate(shown):
        side = verdict(v, band)
        colour = "tab:red" if side in ("below", "above") else "black"
        ax_real.plot([v], [i], "o", color=colour, ms=6)
        ax_real.text(v, i + 0.18, f" {_fmt(v, d.unit)}", fontsize=7, color=colour,
                     va="bottom", ha="left")
    ax_real.set_yticks(range(len(shown)), [n for n, _ in shown], fontsize=9)
    ax_real.set_ylim(-0.7, max(len(shown), 1) - 0.3)
    ax_real.grid(axis="y", color="0.9", lw=0.6)
    ax_real.set_ylabel("real cases (red: outside the band)")
    ax_real.set_xlabel(f"{d.label} ({d.unit})")
    ax_real.set_xlim(lo - pad, hi + pad)
    if missing:
        ax_real.text(0.99, 0.02, f"not measurable: {', '.join(missing)}",
                     transform=ax_real.transAxes, ha="right", va="bottom", fontsize=8)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)


# ------------------------------------------------------------------------------------------
# Main
# ------------------------------------------------------------------------------------------
def _run(jobs: int, fn: Any, items: list[Any], *args: Any, what: str) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=jobs) if jobs > 1 else contextlib.nullcontext() as pool:
        if pool is None:
            results = (fn(item, *args) for item in items)
        else:
            results = (f.result() for f in [pool.submit(fn, item, *args) for item in items])
        for k, row in enumerate(results):
            rows.append(row)
            if what == "real" or (k + 1) % 10 == 0 or k + 1 == len(items):
                tail = f": {row['status']}" if what == "real" else ""
                print(f"[{what} {k + 1}/{len(items)}] {row['name']} in {row['seconds']:.1f} s"
                      f"{tail} ({time.perf_counter() - t0:.0f} s so far)", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", help="real case names (default: all, D2 ... D18)")
    ap.add_argument("--population", type=int, default=200,
                    help="population samples (default 200)")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="first population seed (default 0: the training seeds)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "anatomy_gap",
                    help="output directory (default runs/anatomy_gap)")
    ap.add_argument("--reprepare", action="store_true",
                    help="prepare the real cases again instead of reusing OUT/real")
    ap.add_argument("--jobs", type=int, default=1, help="anatomies measured at once (default 1)")
    args = ap.parse_args(argv)
    if args.population < 2 or args.jobs < 1 or args.first_seed < 0:
        ap.error("expected --population >= 2, --jobs >= 1 and --first-seed >= 0")
    import yaml

    cases = find_cases(args.cases)
    seeds = list(range(args.first_seed, args.first_seed + args.population))
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    print(f"bench_anatomy_gap: {len(cases)} real case(s), {len(seeds)} population seeds "
          f"({seeds[0]}-{seeds[-1]}) -> {args.out} (jobs {args.jobs}, cpus {os.cpu_count()})",
          flush=True)
    real = _run(args.jobs, real_case, cases, args.out, args.reprepare, what="real")
    pop_rows = _run(args.jobs, population_case, seeds, args.out, what="population")
    population = [r["values"] for r in pop_rows]
    band = bands(population)
    seed_text = f"seeds {seeds[0]}-{seeds[-1]}"
    for d in DESCRIPTORS:
        plot(d.key, population, real, band[d.key], args.out / f"{d.key}.png", len(population))
    text = markdown(real, len(population), seed_text, band)
    (args.out / "anatomy_gap.md").write_text(text)
    (args.out / "descriptors.yaml").write_text(yaml.safe_dump({
        "units": {d.key: d.unit for d in DESCRIPTORS},
        "population_band": band,
        "real": {r["name"]: {"status": r["status"],
                             "annulus_uncertainty_mm": r["annulus_uncertainty_mm"],
                             **r.get("values", {})} for r in real},
        "population": {r["name"]: r["values"] for r in pop_rows},
    }, sort_keys=False))
    summary = text.split("## Population")[0]
    print(summary)
    print(f"bench_anatomy_gap: {len(DESCRIPTORS)} figures and anatomy_gap.md in {args.out}; "
          f"{time.perf_counter() - t0:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
