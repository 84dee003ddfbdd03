"""``prepare_anatomy`` on every real patient in the project's copy of the AVT cases, one table.

For each case of ``data/anatomies/avt/`` (11 real CTA whole-aorta segmentations, CC BY 4.0;
see its README for the citation) the bench runs ``prepare_anatomy`` on the dataset's own
``.seg.nrrd`` with its defaults (the expert check included: the scripted expert to every
standard target, static and dynamic), then measures the scripted expert's and the centerline
follower's success on three target sets the check does not use (sets 1-3, every start and
target once per set: 15 trials a set), static and dynamic
(:func:`cgail_patient.validate.expert_success`). It prints, and writes to
``OUT/real_patients.md`` and ``OUT/real_patients.yaml``:

* prepared, or refused (exit 1: the expert check or another check failed; exit 2: the input
  was refused) and why;
* the landmarks: annulus diameter and its uncertainty along the root axis, the descending cut's
  height relative to the annulus and its centreline distance below the last arch branch, the
  ostia's heights, the number of arch branches;
* the time ``prepare_anatomy`` took;
* the expert's and the follower's success, static and dynamic.

    scripts/ws python bench/bench_real_patients.py                 # all 11 cases
    scripts/ws python bench/bench_real_patients.py --cases D18 D2 --trials 5 --jobs 2

Cases run in parallel with ``--jobs`` (one process each); the figures do not depend on it.
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
import io
import math
import os
from pathlib import Path
import re
import sys
import time
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "anatomies" / "avt"


def _case_number(path: Path) -> int:
    m = re.search(r"(\d+)", path.name)
    return int(m.group(1)) if m else 0


def find_cases(names: list[str] | None = None) -> list[Path]:
    """The ``.seg.nrrd`` of every case (or of ``names``), in case order."""
    found = sorted(DATA.glob("D*/D*.seg.nrrd"), key=_case_number)
    if names:
        by_name = {p.parent.name: p for p in found}
        missing = [n for n in names if n not in by_name]
        if missing:
            raise SystemExit(f"bench_real_patients: expected cases among "
                             f"{', '.join(by_name)}, found {', '.join(missing)}")
        found = [by_name[n] for n in names]
    return found


def _landmarks(result: Any) -> dict[str, Any]:
    """Landmark figures of a prepare_anatomy result (mm, from the annulus centre)."""
    prepared = result.prepared
    a = result.anatomy
    axis = np.asarray(a.root_axis, dtype=float)
    exit_mm = np.asarray(a.exit_point, dtype=float) * 1e3
    figures = prepared.figures
    return {
        "annulus_diameter_mm": figures.get("annulus_diameter_mm", math.nan),
        "annulus_uncertainty_mm": float(prepared.annulus_uncertainty_mm),
        "exit_height_mm": float(exit_mm @ axis),
        "exit_below_arch_mm": figures.get("exit_below_arch_mm", math.nan),
        "arch_branches": int(figures.get("arch_branches", -1)),
        "ostia_height_mm": {k: float(np.asarray(o) @ axis * 1e3) for k, o in a.ostia.items()},
        "ostia_source": prepared.sources.get("left_ostium", "?"),
    }


def run_case(seg: Path, out: Path, trials: int) -> dict[str, Any]:
    """prepare_anatomy then the success table of one case (runs in a worker process)."""
    from contextlib import redirect_stderr

    from cgail_patient import PatientError
    from cgail_patient.prepare_cli import prepare_anatomy
    from cgail_patient.validate import expert_success
    from cgail_sim.anatomy import AnatomyError

    name = seg.parent.name
    row: dict[str, Any] = {"case": name}
    t0 = time.perf_counter()
    err = io.StringIO()
    try:
        with redirect_stderr(err):
            result = prepare_anatomy([str(seg), "--out", str(out / name), "--name", name])
    except (PatientError, AnatomyError, OSError) as e:
        row.update(status="refused (exit 2)", why=str(e), seconds=time.perf_counter() - t0)
        return row
    row["seconds"] = time.perf_counter() - t0
    row["warnings"] = list(result.record.get("warnings", []))
    row.update(_landmarks(result))
    if result.usable:
        row["status"] = "prepared"
        row["why"] = ""
    else:
        row["status"] = "refused (exit 1)"
        row["why"] = "; ".join(f"{c.name}: {c.message}" for c in result.validation.errors)
        return row
    rates: dict[str, float] = {}
    faults = 0
    t1 = time.perf_counter()
    for method in ("expert", "follower"):
        table = expert_success(out / name, sets=(1, 2, 3), method=method, trials=trials)
        for mode in ("static", "dynamic"):
            rates[f"{method} {mode}"] = table.rate(mode)
            faults += sum(bool(getattr(t, "simulation_fault", False)
                               or getattr(t, "outcome", "") == "simulation fault")
                          for ts in table.trials[mode].values() for t in ts)
    row["success"] = rates
    row["simulation_faults"] = faults
    row["success_seconds"] = time.perf_counter() - t1
    return row


def _pct(x: float) -> str:
    return "-" if x is None or not math.isfinite(x) else f"{100 * x:.0f}%"


def markdown(rows: list[dict[str, Any]], trials: int) -> str:
    """The table of every case."""
    head = ("| case | result | annulus Ø (mm) | annulus ± (mm) | exit vs annulus (mm) | "
            "exit below arch (mm) | arch branches | ostia L / R (mm) | time (s) | "
            "expert static | expert dynamic | follower static | follower dynamic |")
    lines = [head, "|" + "---|" * 13]
    for r in rows:
        s = r.get("success", {})
        ost = r.get("ostia_height_mm", {})
        lines.append(
            f"| {r['case']} | {r['status']} | {r.get('annulus_diameter_mm', math.nan):.1f} | "
            f"{r.get('annulus_uncertainty_mm', math.nan):.0f} | "
            f"{r.get('exit_height_mm', math.nan):+.0f} | "
            f"{r.get('exit_below_arch_mm', math.nan):.0f} | {r.get('arch_branches', '-')} | "
            f"{ost.get('left', math.nan):.0f} / {ost.get('right', math.nan):.0f} | "
            f"{r['seconds']:.0f} | {_pct(s.get('expert static', math.nan))} | "
            f"{_pct(s.get('expert dynamic', math.nan))} | "
            f"{_pct(s.get('follower static', math.nan))} | "
            f"{_pct(s.get('follower dynamic', math.nan))} |")
    prepared = [r for r in rows if r["status"] == "prepared"]
    lines.append("")
    lines.append(f"{len(prepared)} of {len(rows)} cases prepared. Success: target sets 1-3, "
                 f"{trials} trials a set (every start and target), static and dynamic.")
    for r in rows:
        if r["status"] != "prepared":
            lines.append(f"- {r['case']} {r['status']}: {r['why']}")
    faults = sum(r.get("simulation_faults", 0) for r in rows)
    lines.append(f"- simulation faults in the success trials: {faults}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", nargs="+", help="case names (default: all, D2 ... D18)")
    ap.add_argument("--out", type=Path, default=ROOT / "runs" / "real_patients",
                    help="output directory (default runs/real_patients)")
    ap.add_argument("--trials", type=int, default=15,
                    help="trials per target set and mode (default 15: every pair once)")
    ap.add_argument("--jobs", type=int, default=1, help="cases run at once (default 1)")
    args = ap.parse_args(argv)
    if args.trials < 1 or args.jobs < 1:
        ap.error("expected --trials >= 1 and --jobs >= 1")
    import yaml

    cases = find_cases(args.cases)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    print(f"bench_real_patients: {len(cases)} case(s) -> {args.out} (jobs {args.jobs}, "
          f"cpus {os.cpu_count()})", flush=True)
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        futures = [pool.submit(run_case, seg, args.out, args.trials) for seg in cases]
        for k, fut in enumerate(futures):
            row = fut.result()
            rows.append(row)
            s = row.get("success", {})
            print(f"[{k + 1}/{len(cases)}] {row['case']}: {row['status']} in "
                  f"{row['seconds']:.0f} s"
                  + (f"; expert {_pct(s['expert static'])} / {_pct(s['expert dynamic'])}, "
                     f"follower {_pct(s['follower static'])} / {_pct(s['follower dynamic'])} "
                     "(static / dynamic)" if s else f"; {row['why'][:200]}"), flush=True)
    text = markdown(rows, args.trials)
    (args.out / "real_patients.md").write_text(text)
    (args.out / "real_patients.yaml").write_text(yaml.safe_dump(rows, sort_keys=False))
    print(text)
    print(f"bench_real_patients: {time.perf_counter() - t0:.0f} s in all")
    return 0


if __name__ == "__main__":
    sys.exit(main())
