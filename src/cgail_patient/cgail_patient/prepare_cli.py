"""``cgail prepare-anatomy``: a patient's CT label map or lumen surface in, a prepared anatomy
out.

Usage::

    cgail prepare-anatomy aorta.nii.gz --out runs/patient7 [--label 1] [--lv lv.nii.gz]
                          [--coronary coronaries.nii.gz] [--name patient7]
    cgail prepare-anatomy Segmentation.seg.nrrd --label aorta [--lv-label "left ventricle"] \\
                          --out DIR
    cgail prepare-anatomy total.nii.gz --label total:aorta --out DIR
    cgail prepare-anatomy lumen.stl --frame LPS --out runs/patient7 [--units mm]

Label maps: NIfTI (``.nii``, ``.nii.gz``), NRRD (``.nrrd``, ``.nhdr``) and 3D Slicer
segmentations (``.seg.nrrd``, also multi-layer), in any orientation and with anisotropic voxels
(thick slices are interpolated by shape). ``--label`` / ``--lv-label`` choose the voxels: a label
value (``1``), a Slicer segment name (``aorta``), a TotalSegmentator class (``total:aorta``,
``total:heart``, ``heartchambers_highres:heart_ventricle_left``, ``total_v1:aorta``) or several
joined by commas; by default every non-zero voxel (or a segmentation's only segment).

Writes ``DIR/lumen.stl`` (mm) with its landmark sidecar ``DIR/lumen.yaml`` (the format of
:func:`cgail_sim.anatomy.load_anatomy_mesh`), ``DIR/report.md`` (checks, figures,
landmarks, decisions, warnings), ``DIR/render.png`` and ``DIR/prepare.yaml`` (inputs, options,
versions, the frame conversion and ``Anatomy.content_hash``). Every other tool loads the result
with ``load_anatomy_mesh(DIR / "lumen.stl")``.

The checks (:mod:`cgail_patient.validate`) end with the proof that the anatomy is
usable: the scripted expert drives whole episodes to every standard target, in the rigid and in
the beating aorta (about 10 s); a target it cannot reach refuses the anatomy, and one stderr
line and the report's per-target table say which target, in which mode, from which start, and
why (collision, exit, timeout, simulation fault). ``--no-expert-check`` skips that proof (quick
runs only: the report then says the anatomy's usability is not proven).

Exit status: 0 usable; 1 the checks refused the anatomy (the report and render are written, the
lumen is kept as ``lumen.rejected.stl`` / ``.yaml`` for inspection); 2 the input could not be
used (one line on stderr says why; nothing is written: the directory is made in a hidden
sibling and moved into place only when complete).

Points given on the command line (``--annulus``, ``--exit-point``, ``--left-ostium``,
``--right-ostium``) are in the input's frame and mm: scanner RAS for a NIfTI label map, the
header's ``space`` for a NRRD (LPS for a 3D Slicer file), the declared ``--frame`` for a mesh.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
import datetime
import math
from pathlib import Path
import shutil
import sys
import tempfile
import time
from typing import Any

import numpy as np

from cgail_patient import PatientError
from cgail_patient.prepare import (
    LandmarkOverrides,
    prepare_volume,
    PreparedAnatomy,
    PrepareOptions,
)
from cgail_patient.validate import validate_anatomy, Validation
from cgail_patient.volume import (
    FRAMES,
    LABEL_MAP_SUFFIXES,
    LabelImage,
    LabelVolume,
    LPS_FROM_RAS,
    MESH_SUFFIXES,
    read_label_image,
    read_surface,
    UNITS,
    voxelize_surface,
)
from cgail_sim.anatomy import AnatomyError, load_anatomy_mesh, save_anatomy_mesh
from cgail_sim.cli_help import tool_parser

__all__ = ["PrepareResult", "build_parser", "main", "prepare_anatomy"]

_PROG = "cgail prepare-anatomy"


class PrepareResult:
    """What one ``prepare_anatomy`` run made."""

    def __init__(self, out: Path, prepared: PreparedAnatomy, validation: Validation,
                 anatomy: Any, record: dict[str, Any]) -> None:
        self.out = out
        self.prepared = prepared
        self.validation = validation
        self.anatomy = anatomy
        """The anatomy read back from ``DIR/lumen.stl`` (what every other tool will load)."""
        self.record = record
        """The content of ``prepare.yaml``."""

    @property
    def usable(self) -> bool:
        return not self.validation.errors


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``cgail prepare-anatomy``."""
    ap = tool_parser("prepare-anatomy", __doc__, details=True)
    ap.add_argument("input", help="label map (NIfTI .nii/.nii.gz, NRRD .nrrd/.nhdr, 3D Slicer "
                                  ".seg.nrrd) or closed lumen surface (.stl/.obj/.ply/.vtp)")
    ap.add_argument("--out", required=True, help="directory to write the prepared anatomy to")
    ap.add_argument("--name", default=None, help="anatomy name (default: the directory name)")
    ap.add_argument("--label", default=None,
                    help="the aortic lumen's voxels: a label value, a Slicer segment name, a "
                         "TotalSegmentator class (total:aorta, heartchambers_highres:aorta, "
                         "total_v1:aorta) or several joined by commas (default: every "
                         "non-zero voxel, or a segmentation's only segment)")
    ap.add_argument("--frame", choices=FRAMES, default=None,
                    help="axes of a surface mesh's coordinates (required for a mesh)")
    ap.add_argument("--units", choices=sorted(UNITS), default="mm",
                    help="length unit of a surface mesh (default mm)")
    ap.add_argument("--lv", default=None,
                    help="left-ventricle label map (any label-map format): the annulus plane "
                         "is fitted to its contact with the aorta")
    ap.add_argument("--lv-label", default=None,
                    help="the LV's voxels in --lv, chosen as --label (e.g. "
                         "heartchambers_highres:heart_ventricle_left; default: every non-zero "
                         "voxel); without --lv, the LV is read from the input label map")
    ap.add_argument("--coronary", default=None,
                    help="coronary label map (any label-map format): the ostia are where the "
                         "two coronary arteries meet the aorta")
    for key in ("annulus", "exit-point", "left-ostium", "right-ostium"):
        ap.add_argument(f"--{key}", type=float, nargs=3, metavar=("X", "Y", "Z"), default=None,
                        help=f"the {key.replace('-', ' ')} (input frame, mm), instead of the "
                             "estimate")
    d = PrepareOptions()
    ap.add_argument("--target-vertices", type=int, default=d.target_vertices,
                    help=f"vertex count of the lumen (default {d.target_vertices})")
    ap.add_argument("--branch-mm", type=float, default=d.branch_mm,
                    help=f"supra-aortic branch length kept beyond the wall (default "
                         f"{d.branch_mm:g} mm)")
    ap.add_argument("--descending-mm", type=float, default=d.descending_mm,
                    help=f"centreline kept below the last branch (default {d.descending_mm:g} mm)")
    ap.add_argument("--smoothing-mm", type=float, default=d.smoothing_mm,
                    help=f"Gaussian smoothing of the lumen (default {d.smoothing_mm:g} mm)")
    ap.add_argument("--voxel-mm", type=float, default=None,
                    help="working voxel size (default: the label map's, within 0.5-1 mm; "
                         "0.75 mm for a mesh)")
    ap.add_argument("--no-wall-check", action="store_true",
                    help="skip the deformable-wall check (two simulated heartbeats)")
    ap.add_argument("--no-expert-check", action="store_true",
                    help="skip the expert check, the proof that the anatomy is usable (the "
                         "scripted expert to every standard target, static and dynamic; "
                         "~15 s): for quick runs only")
    return ap


def _versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {}
    for pkg in ("cgail_planner", "numpy", "scipy", "scikit-image", "nibabel", "pynrrd", "trimesh",
                "fast-simplification"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def _read_inputs(args: argparse.Namespace) -> tuple[LabelVolume, np.ndarray, str, list[str],
                                                    dict[str, Any], LabelImage | None]:
    """(lumen volume, matrix input -> LPS, frame name, notes, input record, the label map as
    read or None for a mesh)."""
    path = Path(args.input)
    name = path.name.lower()
    notes: list[str] = []
    if name.endswith(LABEL_MAP_SUFFIXES):
        image = read_label_image(path)
        if args.frame is not None:
            notes.append(f"--frame ignored: the {image.kind} file gives its own frame "
                         f"({image.frame})")
        vol = image.volume(args.label, spacing=args.voxel_mm)
        notes += image.notes
        how = ("NIfTI affine" if image.kind == "NIfTI" else "NRRD space")
        record = {"kind": "label map", "format": image.kind, "path": str(path.resolve()),
                  "label": args.label, "selected": vol.source,
                  "frame": f"{image.frame} ({how})",
                  "input_voxel_mm": [round(float(x), 4) for x in
                                     np.linalg.norm(image.affine[:3, :3], axis=0)],
                  "working_voxel_mm": vol.spacing}
        return vol, image.to_lps, image.frame, notes, record, image
    if not name.endswith(MESH_SUFFIXES):
        raise PatientError(f"expected a label map ({', '.join(LABEL_MAP_SUFFIXES)}) or a surface "
                           f"mesh ({', '.join(MESH_SUFFIXES)}), found {path.name!r}")
    if args.lv is None and args.lv_label is not None:
        raise PatientError(f"expected --lv with --lv-label for the surface mesh {path.name}, "
                           "found none (a mesh has no labels)")
    if args.frame is None:
        raise PatientError(f"expected --frame RAS or --frame LPS for the surface mesh "
                           f"{path.name} (a mesh's coordinates carry no axis convention), "
                           "found none")
    surface = read_surface(path, frame=args.frame, units=args.units)
    vol = voxelize_surface(surface, spacing=args.voxel_mm or 0.75)
    record = {"kind": "surface mesh", "path": str(path.resolve()), "frame": args.frame,
              "units": args.units, "vertices": len(surface.vertices),
              "working_voxel_mm": vol.spacing}
    to_lps = LPS_FROM_RAS if args.frame == "RAS" else np.eye(3)
    return vol, to_lps, args.frame, notes, record, None


def _extra_map(source: str | LabelImage, label: str | None, vol: LabelVolume,
               what: str) -> LabelVolume:
    """The ``what`` voxels (``label`` of ``source``, a file or the input's label map) on the
    lumen's grid."""
    image = source if isinstance(source, LabelImage) else read_label_image(source)
    hi = vol.origin + vol.spacing * (np.array(vol.mask.shape) - 1)
    try:
        extra = image.volume(label, spacing=vol.spacing, bbox_lps=(vol.origin, hi))
    except PatientError as err:
        raise PatientError(f"{what} label map: {err}") from err
    if not extra.mask.any():
        raise PatientError(f"expected {what} voxels of {extra.source} within the aortic "
                           "label's bounding box (+15 mm), found none: not the same patient "
                           "or frame?")
    return extra


class _Staging:
    """The output directory made in a hidden sibling and moved into place when complete, so a
    run that fails leaves no half-written directory (and an earlier run's files untouched)."""

    def __init__(self, final: Path) -> None:
        self.final = final
        self.path: Path | None = None

    def make(self) -> Path:
        """Create the staging directory (and the output's parent) and return it."""
        self.final.parent.mkdir(parents=True, exist_ok=True)
        self.path = Path(tempfile.mkdtemp(prefix=f".{self.final.name}.", suffix=".partial",
                                          dir=self.final.parent))
        return self.path

    def publish(self) -> None:
        """Move the staged files into the output directory: a new directory is renamed into
        place; into an existing one each file replaces its namesake (and the other lumen
        files of an earlier run are removed)."""
        if self.path is None:
            return
        if not self.final.exists():
            self.path.rename(self.final)
        else:
            for stale in ("lumen.stl", "lumen.yaml", "lumen.rejected.stl",
                          "lumen.rejected.yaml"):
                if not (self.path / stale).exists():
                    (self.final / stale).unlink(missing_ok=True)
            for f in sorted(self.path.iterdir()):
                f.replace(self.final / f.name)
            self.path.rmdir()
        self.path = None

    def discard(self) -> None:
        """Remove what is still staged (after a failure)."""
        if self.path is not None:
            shutil.rmtree(self.path, ignore_errors=True)
            self.path = None


def prepare_anatomy(argv: Sequence[str] | None = None) -> PrepareResult:
    """Run ``prepare_anatomy`` (the command line's arguments) and return what it made.

    Raises:
        PatientError: the input cannot be used (one line why); nothing is written.
        AnatomyError: the written lumen does not load back (a bug: report it).
    """
    args = build_parser().parse_args(argv)
    stage = _Staging(Path(args.out))
    if stage.final.exists() and not stage.final.is_dir():
        raise PatientError(f"expected --out to be a directory, found a file at {stage.final}")
    try:
        result = _prepare(args, argv, stage)
        stage.publish()
    finally:
        stage.discard()
    result.out = stage.final
    return result


def _prepare(args: argparse.Namespace, argv: Sequence[str] | None,
             stage: _Staging) -> PrepareResult:
    """:func:`prepare_anatomy` writing into ``stage``."""
    t_start = time.perf_counter()
    out = Path(args.out)
    name = args.name or out.resolve().name
    try:
        options = PrepareOptions(target_vertices=args.target_vertices, branch_mm=args.branch_mm,
                                 descending_mm=args.descending_mm,
                                 smoothing_mm=args.smoothing_mm)
    except ValueError as err:
        raise PatientError(str(err)) from err
    t0 = time.perf_counter()
    vol, to_lps, frame, in_notes, in_record, image = _read_inputs(args)
    lv_source = args.lv or (image if args.lv_label is not None else None)
    lv = (_extra_map(lv_source, args.lv_label, vol, "left-ventricle")
          if lv_source is not None else None)
    cor = _extra_map(args.coronary, None, vol, "coronary") if args.coronary else None
    t_read = time.perf_counter() - t0

    def lps(point: Sequence[float] | None) -> np.ndarray | None:
        return None if point is None else to_lps @ np.asarray(point, dtype=float)

    overrides = LandmarkOverrides(annulus_center=lps(args.annulus),
                                  exit_point=lps(args.exit_point),
                                  left_ostium=lps(args.left_ostium),
                                  right_ostium=lps(args.right_ostium))
    hint = ("check --frame" if in_record["kind"] == "surface mesh"
            else "check the NIfTI affine (orientation)" if image is not None
            and image.kind == "NIfTI" else "check the NRRD space and space directions")
    prepared = prepare_volume(vol, name=name, options=options, lv=lv, coronary=cor,
                              overrides=overrides, frame_hint=hint)
    prepared.timings = {"read input": t_read, **prepared.timings}
    prepared.notes[:0] = in_notes
    out = stage.make()
    save_anatomy_mesh(prepared.anatomy, out / "lumen.stl")
    anatomy = load_anatomy_mesh(out / "lumen.stl", name=name)
    t0 = time.perf_counter()
    validation = validate_anatomy(anatomy, wall=not args.no_wall_check,
                                  expert=not args.no_expert_check)
    prepared.timings["validation"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    _render(anatomy, prepared, validation, out / "render.png")
    prepared.timings["render"] = time.perf_counter() - t0
    prepared.timings["total"] = time.perf_counter() - t_start
    to_input = np.linalg.inv(to_lps)
    record = {
        "name": name,
        "created": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "command": [*_PROG.split(), *(sys.argv[1:] if argv is None else list(argv))],
        "input": in_record,
        "lv": None if lv_source is None else {
            "path": str(Path(args.lv or args.input).resolve()), "label": args.lv_label},
        "coronary": None if args.coronary is None else str(Path(args.coronary).resolve()),
        "options": {"target_vertices": options.target_vertices, "branch_mm": options.branch_mm,
                    "descending_mm": options.descending_mm,
                    "smoothing_mm": options.smoothing_mm},
        "overrides_input_frame_mm": {k: v for k, v in (
            ("annulus", args.annulus), ("exit_point", args.exit_point),
            ("left_ostium", args.left_ostium), ("right_ostium", args.right_ostium))
            if v is not None},
        "frame_conversion": {
            "input_frame": frame,
            "phantom_from_input": "p_phantom_m = R @ (p_input_mm - t_input_mm) / 1000",
            "R": to_lps.tolist(),
            "t_input_mm": [round(float(x), 4) for x in to_input @ prepared.annulus_lps_mm],
        },
        "landmark_sources": prepared.sources,
        "anatomy": {"vertices": len(anatomy.vertices), "faces": len(anatomy.faces),
                    "content_hash": anatomy.content_hash},
        "usable": not validation.errors,
        "expert_check": _expert_record(validation, args.no_expert_check),
        "errors": [f"{c.name}: {c.message}" for c in validation.errors],
        "warnings": prepared.warnings + [f"{c.name}: {c.message}" for c in validation.warnings],
        "timings_s": {k: round(v, 2) for k, v in prepared.timings.items()},
        "versions": _versions(),
    }
    import yaml

    (out / "prepare.yaml").write_text(yaml.safe_dump(record, sort_keys=False))
    (out / "report.md").write_text(_report(record, prepared, validation, anatomy, to_input))
    if validation.errors:
        (out / "lumen.stl").rename(out / "lumen.rejected.stl")
        (out / "lumen.yaml").rename(out / "lumen.rejected.yaml")
    return PrepareResult(out, prepared, validation, anatomy, record)


def _render(anatomy: Any, prepared: PreparedAnatomy, validation: Validation, path: Path) -> None:
    from cgail_sim.render import render_anatomy

    n_err = len(validation.errors)
    verdict = "usable" if not n_err else f"NOT usable ({n_err} error{'s' * (n_err > 1)})"
    render_anatomy(
        anatomy, path, centerlines=validation.centerlines,
        scenarios=validation.scenarios is not None,
        markers={"annulus centre": np.asarray(anatomy.annulus_center),
                 "exit point": np.asarray(anatomy.exit_point), **_missed_targets(validation)},
        title=f"prepared anatomy '{anatomy.name}': {len(anatomy.vertices)} vertices; {verdict}")


def _fmt(p: np.ndarray) -> str:
    return "(" + ", ".join(f"{float(x):.1f}" for x in p) + ")"


def _report(record: dict[str, Any], prepared: PreparedAnatomy, v: Validation, anatomy: Any,
            to_input: np.ndarray) -> str:
    name = record["name"]
    errors = v.errors
    lines = [f"# Prepared anatomy `{name}`", ""]
    if errors:
        lines += [f"**NOT usable: {len(errors)} error(s).** The lumen is kept as "
                  "`lumen.rejected.stl` for inspection only.", ""]
        lines += [f"- **{c.name}**: {c.message}" for c in errors] + [""]
    else:
        lines += ["**Usable.** Load it with `load_anatomy_mesh(DIR / 'lumen.stl')`; "
                  f"content hash `{anatomy.content_hash}`.", ""]
    inp = record["input"]
    lines += ["## Input", "", "| | |", "|---|---|"]
    lines += [f"| {k.replace('_', ' ')} | {val} |" for k, val in inp.items()]
    lines += [f"| left ventricle | {record['lv']['path'] if record['lv'] else 'none'} |",
              f"| coronary arteries | {record['coronary'] or 'none'} |",
              f"| command | `{' '.join(record['command'])}` |", ""]
    conv = record["frame_conversion"]
    lines += ["## Frame conversion", "",
              f"Input frame **{conv['input_frame']}** (mm) to the simulator's `phantom` frame "
              "(m; x patient left, y posterior, z cranial; annulus centre at the origin):", "",
              f"    p_phantom = R (p_input - t) / 1000,   R = {conv['R']},   "
              f"t = {conv['t_input_mm']} mm", ""]
    lines += ["## Checks", "", "| check | result | value | limit |", "|---|---|---|---|"]
    for c in v.checks:
        mark = {"ok": "ok", "warning": "**warning**", "error": "**ERROR**"}[c.status]
        lines.append(f"| {c.name} | {mark} | {c.value} | {c.limit} |")
    lines.append("")
    for c in v.checks:
        if c.status != "ok":
            lines.append(f"- {c.status}: **{c.name}**: {c.message}")
    lines += [""]
    lines += ["## Landmarks", "",
              "| landmark | phantom (mm) | input frame (mm) | source |", "|---|---|---|---|"]
    t_in = np.asarray(conv["t_input_mm"])
    for key, p, src in (
            ("annulus centre", anatomy.annulus_center, prepared.sources.get("annulus_center")),
            ("exit point", anatomy.exit_point, prepared.sources.get("exit_point")),
            ("left ostium", anatomy.ostia["left"], prepared.sources.get("left_ostium")),
            ("right ostium", anatomy.ostia["right"], prepared.sources.get("right_ostium")),
            ("start point", anatomy.start_point, "20 mm above the exit on the centreline")):
        p_mm = np.asarray(p) * 1e3
        lines.append(f"| {key} | {_fmt(p_mm)} | {_fmt(to_input @ p_mm + t_in)} | {src} |")
    lines.append(f"| root axis | {_fmt(anatomy.root_axis)} (unit) | "
                 f"{_fmt(to_input @ anatomy.root_axis)} | valve plane |")
    lines += ["", "Cuts (input frame, mm):", ""]
    for cut in prepared.cuts:
        lines.append(f"- {cut.name}: centre {_fmt(to_input @ cut.point)}, radius "
                     f"{cut.radius:.1f} mm")
    prof = v.figures.get("radius_profile")
    if prof:
        lines += ["", "## Lumen radius along the centrelines", "",
                  "Inscribed radius (mm) every 25 mm from the start; the last 10 mm into the "
                  "ostium are left out.", "",
                  "| centreline | min | median | profile |", "|---|---|---|---|"]
        for b, p in prof.items():
            arc = np.asarray(p["arc_mm"])
            r = np.asarray(p["radius_mm"])
            marks = np.arange(0.0, arc[-1] + 1e-9, 25.0)
            samples = " ".join(f"{np.interp(s, arc, r):.1f}" for s in marks)
            lines.append(f"| {b} ({record_len(v, b)}) | {p['min']:.1f} | {p['median']:.1f} | "
                         f"{samples} |")
    lines += ["", "## What was decided", ""] + [f"- {n}" for n in prepared.notes]
    warns = record["warnings"]
    lines += ["", "## Warnings", ""] + ([f"- {w}" for w in warns] if warns else ["none"])
    lines += _expert_section(v)
    lines += ["", "## Timings", "", "| step | s |", "|---|---|"]
    lines += [f"| {k} | {val:.1f} |" for k, val in prepared.timings.items()]
    lines += ["", "## Render", "", "Lumen (wall red, caps grey), centrelines, ostia, annulus "
              "centre, exit point, starts (triangles) and targets (stars):", "",
              "![render](render.png)", ""]
    return "\n".join(lines)


def _expert_record(v: Validation, skipped: bool) -> Any:
    """The expert check in ``prepare.yaml``: one entry per episode, or why there is none."""
    if skipped:
        return "skipped (--no-expert-check): usability not proven"
    if not v.expert_trials:
        return "not run"
    return [{"mode": t.mode, "target": t.target, "start": t.start, "outcome": t.outcome,
             "steps": t.steps, "final_distance_mm": round(t.final_distance_mm, 2),
             "max_wall_displacement_mm": round(t.max_wall_mm, 2), "detail": t.detail}
            for t in v.expert_trials]


def _missed_targets(v: Validation) -> dict[str, np.ndarray]:
    """Render markers at the targets the expert check did not reach (rest positions)."""
    if v.scenarios is None:
        return {}
    reached = {(t.mode, t.target) for t in v.expert_trials if t.outcome == "success"}
    missed: dict[int, list[str]] = {}
    for t in v.expert_trials:
        if (t.mode, t.target) not in reached and t.mode not in missed.get(t.target, []):
            missed.setdefault(t.target, []).append(t.mode)
    return {f"target {k} NOT reached ({', '.join(modes)})":
            np.asarray(v.scenarios.targets[k].position) for k, modes in missed.items()}


def _expert_section(v: Validation) -> list[str]:
    """The report's per-episode table of the expert check."""
    lines = ["", "## Scripted expert to every standard target", ""]
    if not v.expert_trials:
        ran = [c for c in v.checks if c.name.startswith("expert ")]
        lines.append("Not run: " + (ran[0].message.removeprefix("not run: ") if ran else
                                    "skipped (`--no-expert-check`); the anatomy's usability "
                                    "is not proven."))
        return lines
    lines += ["Target k of set 0 from start k % 3 (another start when that fails), whole "
              "episodes of the real env: rigid wall (static), then the beating wall pushed by "
              "the catheter body with the target riding on it (dynamic). Target positions from "
              "the annulus centre (x patient left, y posterior, z cranial), height above the "
              "annulus plane. Wall: the largest wall-particle displacement from rest.", "",
              "| mode | target | position (mm) | height (mm) | start | outcome | steps | "
              "final distance (mm) | closest (mm) | wall (mm) | tip-contact steps | why |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for t in v.expert_trials:
        mark = t.outcome if t.outcome == "success" else f"**{t.outcome}**"
        wall = f"{t.max_wall_mm:.1f}" if t.mode == "dynamic" else "-"
        lines.append(f"| {t.mode} | {t.target} | {_fmt(np.asarray(t.target_mm))} | "
                     f"{t.height_mm:.1f} | {t.start} | {mark} | {t.steps} | "
                     f"{t.final_distance_mm:.1f} | {t.closest_mm:.1f} | {wall} | "
                     f"{t.contact_steps} | {t.detail} |")
    return lines


def record_len(v: Validation, branch: str) -> str:
    """Centreline length of ``branch`` as text."""
    length = v.figures.get("centerline_length_mm", {}).get(branch)
    return "?" if length is None or not math.isfinite(length) else f"{length:.0f} mm"


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail prepare-anatomy``; returns the exit status (module doc)."""
    try:
        result = prepare_anatomy(argv)
    except (PatientError, AnatomyError, OSError) as err:
        print(f"{_PROG}: error: {err}", file=sys.stderr)
        return 2
    v = result.validation
    for c in v.errors:
        print(f"{_PROG}: error: {c.name}: {c.message}", file=sys.stderr)
    for w in result.record["warnings"]:
        print(f"{_PROG}: warning: {w}", file=sys.stderr)
    a = result.anatomy
    lengths = v.figures.get("centerline_length_mm", {})
    print(f"{_PROG}: {'usable' if result.usable else 'NOT usable'}: {result.out} "
          f"({len(a.vertices)} vertices, centrelines "
          f"{' / '.join(f'{x:.0f}' for x in lengths.values())} mm, "
          f"{result.prepared.timings['total']:.0f} s); see {result.out / 'report.md'}")
    return 0 if result.usable else 1


if __name__ == "__main__":
    sys.exit(main())
