"""``cgail plan-patient`` end to end on the project's synthetic patients: time and success on
unseen targets.

Run: ``scripts/ws python bench/bench_plan_patient.py [--budget-min 15] [--out runs/bench_plan]
[--patients ct mesh]``.

Two patients, each in a scanner frame, made by :mod:`cgail_patient.synthetic` (nothing is
downloaded):

* ``ct``: a CT label map of the ``elongated`` aorta (0.84 x 0.84 x 1.0 mm voxels, LPS voxel order,
  partial-volume noise, long supra-aortic branches, a left-ventricle map), the anatomy on which
  the committed default policy reaches 0% (it was trained on ``default``);
* ``mesh``: a noisy lumen surface (0.3 mm vertex noise) of the ``default`` aorta in RAS.

Each goes through ``cgail prepare-anatomy`` and then ``cgail plan-patient --budget-min B`` (its
whole pipeline: expert demonstrations, a behavioural-cloning warm start, a DAgger round when the
warm start validates under the static goal plus 5 points, and C-GAIL fine-tuning from the
committed policy, export, evaluation on unseen target sets with the centerline follower). Prints
one line per stage and the table docs/reports/patients.md shows; writes ``OUT/bench.md``. The
machine, its cores and its load are printed with the figures, since training speed is what the
budget buys.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from pathlib import Path
import platform
import shutil
import sys
import time

PATIENTS = {
    "ct": ("elongated", ["--voxel-order", "LPS"], "CT label map (LPS), elongated aorta"),
    "mesh": ("default", ["--mesh", "RAS", "--noise-mm", "0.3"],
             "noisy surface mesh (RAS), default aorta"),
}


def cpu_name() -> str:
    """The CPU model (Linux), else the platform's processor string."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--budget-min", type=float, default=15.0)
    p.add_argument("--out", type=Path, default=Path("runs/bench_plan"))
    p.add_argument("--patients", nargs="+", choices=sorted(PATIENTS), default=["ct", "mesh"])
    p.add_argument("--trials", type=int, default=15, help="evaluation trials per test set")
    args = p.parse_args(argv)
    import yaml

    from cgail_patient.plan import main as plan_main
    from cgail_patient.plan import PlanOptions
    from cgail_patient.prepare_cli import main as prepare_main
    from cgail_patient.synthetic import main as synthetic_main

    load0 = os.getloadavg()[0]
    print(f"machine: {cpu_name()}, {os.cpu_count()} logical CPUs, load {load0:.1f}; budget "
          f"{args.budget_min:g} min", flush=True)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name in args.patients:
        anatomy, extra, what = PATIENTS[name]
        base = args.out / name
        shutil.rmtree(base, ignore_errors=True)
        t0 = time.monotonic()
        if synthetic_main(["--out", str(base / "input"), "--anatomy", anatomy, *extra]) != 0:
            return 1
        inputs = sorted((base / "input").glob("*.nii.gz")) + sorted(
            (base / "input").glob("*.stl"))
        if name == "ct":
            cmd = [str(base / "input" / "synthetic_aorta.nii.gz"), "--lv",
                   str(base / "input" / "synthetic_lv.nii.gz")]
        else:
            cmd = [str(inputs[0]), "--frame", "RAS"]
        status = prepare_main([*cmd, "--out", str(base / "anatomy"), "--name", f"syn_{name}"])
        t_prep = time.monotonic() - t0
        print(f"{name}: cgail prepare-anatomy exit {status}, {t_prep:.0f} s", flush=True)
        if status != 0:
            return 1
        t1 = time.monotonic()
        status = plan_main([str(base / "anatomy"), "--out", str(base / "plan"), "--budget-min",
                            f"{args.budget_min:g}", "--trials", str(args.trials),
                            "--no-progress"])
        t_plan = time.monotonic() - t1
        if status == 2:
            return 1
        rec = yaml.safe_load((base / "plan" / "plan.yaml").read_text())
        s = rec["success_unseen_targets"]
        t = rec["timings_s"]
        n = args.trials * len(PlanOptions().test_seeds)
        rows.append(
            f"| {what} | {t_prep:.0f} s | {t['demonstrations']:.0f} s | {t['training']:.0f} s | "
            f"{t_plan:.0f} s | {100 * s['static']['C-GAIL (this run)']:.0f}% "
            f"({100 * s['static']['C-GAIL (base, not tuned)']:.0f}%) | "
            f"{100 * s['dynamic']['C-GAIL (this run)']:.0f}% | "
            f"{100 * s['static']['centerline']:.0f}% / {100 * s['dynamic']['centerline']:.0f}% | "
            f"{'yes' if rec['goals_met'] else 'no'} |")
        print(f"{name}: cgail plan-patient exit {status}, {t_plan:.0f} s; static "
              f"{100 * s['static']['C-GAIL (this run)']:.0f}%, dynamic "
              f"{100 * s['dynamic']['C-GAIL (this run)']:.0f}% ({n} trials each)", flush=True)
    table = [
        f"cgail plan-patient, budget {args.budget_min:g} min, on {cpu_name()} ({os.cpu_count()} "
        f"logical CPUs, load {load0:.1f} at the start); success on unseen targets "
        f"({args.trials * len(PlanOptions().test_seeds)} trials per mode, simulated EM "
        "tracker noise):", "",
        "| patient | prepare_anatomy | demonstrations | training | plan_patient total | "
        "static (base policy untuned) | dynamic | centerline static / dynamic | goals met |",
        "|---|---|---|---|---|---|---|---|---|", *rows]
    (args.out / "bench.md").write_text("\n".join(table) + "\n")
    print("\n".join(table))
    return 0


if __name__ == "__main__":
    sys.exit(main())
