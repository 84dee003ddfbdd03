"""What every CLI, node and config accepts as an anatomy, and the one resolver that makes it an
:class:`~cgail_sim.anatomy.Anatomy`.

An anatomy argument (:data:`AnatomySpec`) is a built-in name
(:data:`~cgail_sim.anatomy.ANATOMY_NAMES`), a population sample ``population-<seed>``
(:mod:`cgail_sim.population`), a real patient's aorta ``avt-<case>`` (:data:`REAL_NAMES`:
prepared AVT cases shipped in this package, ``anatomies/avt/README.md``), a prepared anatomy
directory, a mesh file with its landmarks, or an :class:`~cgail_sim.anatomy.Anatomy`.
:func:`resolve_anatomy` turns it into the anatomy, :func:`check_anatomy_spec` checks it
without loading it, :func:`anatomy_label` and :func:`anatomy_identity` name it.

The resolver sits above both :mod:`~cgail_sim.anatomy` (the anatomy, its generator and
the mesh loader) and :mod:`~cgail_sim.population` (samples built with that generator),
so neither of them imports the other.
"""

from __future__ import annotations

import os
from pathlib import Path

from cgail_sim import population
from cgail_sim.anatomy import (
    Anatomy,
    ANATOMY_NAMES,
    AnatomyError,
    build_anatomy,
    load_anatomy_mesh,
)

__all__ = [
    "MESH_SUFFIXES",
    "PREPARED_MESH",
    "REAL_HELD_OUT",
    "REAL_NAMES",
    "REJECTED_MESH",
    "TRAINING_NAMES",
    "AnatomySpec",
    "anatomy_identity",
    "anatomy_label",
    "check_anatomy_spec",
    "is_builtin",
    "is_named",
    "real_anatomy_dir",
    "resolve_anatomy",
]

#: What every CLI, node and config accepts as an anatomy: a built-in name
#: (:data:`ANATOMY_NAMES`), a prepared anatomy directory, a mesh file, or an :class:`Anatomy`.
AnatomySpec = str | os.PathLike[str] | Anatomy
#: The lumen mesh of a prepared anatomy directory (its landmarks: ``lumen.yaml`` beside it).
PREPARED_MESH = "lumen.stl"
#: What ``prepare_anatomy`` renames the mesh of an anatomy that fails its validation to.
REJECTED_MESH = "lumen.rejected.stl"
#: File types :func:`load_anatomy_mesh` reads.
MESH_SUFFIXES = (".stl", ".obj", ".ply")

#: The folder of the real aortas shipped in this package (one prepared directory per case).
_REAL_DIR = Path(__file__).resolve().parent / "anatomies" / "avt"
_REAL_PREFIX = "avt-"
#: The real patients' aortas every anatomy argument takes by name: ``avt-<case>`` for each
#: prepared AVT case shipped in ``cgail_sim/anatomies/avt`` (CC BY 4.0), in case order.
REAL_NAMES: tuple[str, ...] = tuple(
    _REAL_PREFIX + d.name for d in sorted(
        (d for d in _REAL_DIR.glob("D*") if (d / PREPARED_MESH).is_file()),
        key=lambda d: int(d.name[1:]) if d.name[1:].isdigit() else 0))
#: The real aortas no generalist trains on (its zero-shot test set), chosen by a rule before
#: any training with real aortas: every other case of :data:`REAL_NAMES`, from the second.
REAL_HELD_OUT: tuple[str, ...] = ("avt-D4", "avt-D10", "avt-D13", "avt-D15", "avt-D18")
#: The named anatomies a population run (and its demonstrations) may add to its pool beside the
#: population samples: the built-in ones and the real ones not held out.
TRAINING_NAMES: tuple[str, ...] = (*ANATOMY_NAMES,
                                   *(n for n in REAL_NAMES if n not in REAL_HELD_OUT))

_PATH_CACHE: dict[tuple[str, tuple[int, int], tuple[int, int]], Anatomy] = {}
_PATH_CACHE_MAX = 8


def _usage(spec: object) -> str:
    found = repr(spec) if isinstance(spec, (str, os.PathLike)) else \
        f"an object of type {type(spec).__name__}"  # (never an arbitrary repr: no array dumps)
    return (f"expected a built-in anatomy name {list(ANATOMY_NAMES)}, a population sample "
            f"population-<seed>, a real aorta avt-<case> ({', '.join(REAL_NAMES)}), "
            f"a prepared anatomy directory (holding {PREPARED_MESH} and "
            f"lumen.yaml) or a mesh file ({'/'.join(MESH_SUFFIXES)} in mm, with its <stem>.yaml "
            f"landmarks), found {found}")


def _mesh_of(spec: str | os.PathLike[str]) -> Path:
    """The mesh file an anatomy path stands for (checked to exist, with its sidecar)."""
    path = Path(spec).expanduser()
    if not path.exists():
        raise AnatomyError(f"{_usage(str(spec))}: no such file or directory")
    if path.is_dir():
        mesh = path / PREPARED_MESH
        missing = [f.name for f in (mesh, mesh.with_suffix(".yaml")) if not f.is_file()]
        if missing and (path / REJECTED_MESH).is_file():
            raise AnatomyError(
                f"anatomy {path}: expected a usable prepared anatomy ({PREPARED_MESH}), found "
                f"one cgail prepare-anatomy refused ({REJECTED_MESH}; the reasons are in "
                f"{path / 'report.md'})")
        if missing:
            raise AnatomyError(
                f"anatomy {path}: expected a prepared anatomy directory holding {PREPARED_MESH} "
                f"and lumen.yaml (cgail prepare-anatomy makes one), found no "
                f"{' and no '.join(missing)}")
        return mesh
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise AnatomyError(f"anatomy {path}: expected a mesh file ({'/'.join(MESH_SUFFIXES)}) "
                           f"or a prepared anatomy directory, found a {path.suffix or 'bare'} "
                           "file")
    if not path.with_suffix(".yaml").is_file():
        raise AnatomyError(f"anatomy {path}: expected its landmarks in "
                           f"{path.with_suffix('.yaml')}, found no such file")
    return path


def anatomy_label(spec: AnatomySpec) -> str:
    """A short, stable label of an anatomy, for file names, reports and contracts.

    A built-in name is its own label; a prepared directory's label is its name
    (``runs/patients/p07`` -> ``p07``), a mesh file's its stem (``lumen.stl`` inside a
    directory: the directory's name); an :class:`Anatomy`'s, its name. Only the characters
    ``[A-Za-z0-9._-]`` are kept. The label does not identify the mesh: two directories may
    share a name; :attr:`Anatomy.content_hash` tells them apart.
    """
    if isinstance(spec, Anatomy):
        raw = spec.name
    elif is_named(spec):
        raw = str(spec)
    else:
        path = Path(spec).expanduser().resolve()
        if path.is_dir() or path.suffix.lower() not in MESH_SUFFIXES:
            raw = path.name
        else:
            raw = path.parent.name if path.name == PREPARED_MESH else path.stem
    label = "".join(ch if ch.isalnum() or ch in "._-" else "_" for ch in raw).strip("._")
    return label or "anatomy"


def check_anatomy_spec(spec: AnatomySpec) -> None:
    """Check an anatomy argument without loading it: a built-in name, an :class:`Anatomy`, or
    a path to a prepared directory or a mesh file with its landmarks (configs call this, so a
    bad argument fails where it is given; :func:`resolve_anatomy` loads it).

    Raises:
        AnatomyError: what :func:`resolve_anatomy` raises before it reads a mesh.
    """
    if isinstance(spec, Anatomy) or is_named(spec):
        return
    if not isinstance(spec, (str, os.PathLike)) or (isinstance(spec, str) and not spec.strip()):
        raise AnatomyError(_usage(spec))
    _mesh_of(spec)


def anatomy_identity(spec: AnatomySpec) -> tuple[str, str]:
    """``(label, content_hash)``: what identifies an anatomy in a policy contract or a report.

    A built-in anatomy is identified by its name, with no hash (``""``): its mesh differs in
    the last bits between CPUs (:mod:`cgail_sim.disk_cache`), so a policy trained on
    ``default`` runs on every machine's ``default``. Any other anatomy (a path, an
    :class:`Anatomy` built from parameters) is identified by its content hash, with
    :func:`anatomy_label` as its readable name.
    """
    if is_builtin(spec):
        return str(spec), ""
    anatomy = resolve_anatomy(spec)
    if anatomy.name in ANATOMY_NAMES and anatomy is build_anatomy(anatomy.name):
        return anatomy.name, ""
    return anatomy_label(spec), anatomy.content_hash


def is_builtin(spec: AnatomySpec) -> bool:
    """True when ``spec`` names a built-in anatomy (a string in :data:`ANATOMY_NAMES`)."""
    return isinstance(spec, str) and spec in ANATOMY_NAMES


def is_named(spec: AnatomySpec) -> bool:
    """True when ``spec`` is an anatomy's name rather than a path: a built-in name, a
    population sample's ``population-<seed>`` (both rebuilt by the code, no file behind them)
    or a shipped real aorta's ``avt-<case>`` (:data:`REAL_NAMES`)."""
    return is_builtin(spec) or _population_seed(spec) is not None or real_anatomy_dir(spec) \
        is not None


def real_anatomy_dir(spec: object) -> Path | None:
    """The prepared directory of a shipped real aorta's name (``avt-D18``), else None."""
    if isinstance(spec, str) and spec in REAL_NAMES:
        return _REAL_DIR / spec[len(_REAL_PREFIX):]
    return None


def _population_seed(spec: object) -> int | None:
    """The seed of a population sample's name (``population-<seed>``), else None."""
    return population.population_seed(spec) if isinstance(spec, str) else None


def resolve_anatomy(spec: AnatomySpec) -> Anatomy:
    """The anatomy an argument stands for: the one resolver every CLI, node and config uses.

    Args:
        spec: a built-in name (:data:`ANATOMY_NAMES`; a name wins over a directory of the same
            name: write ``./default`` for that), a population sample ``population-<seed>``
            (:func:`cgail_sim.population.sample_anatomy`, the same rule), a shipped real
            aorta ``avt-<case>`` (:data:`REAL_NAMES`: its prepared directory), a prepared
            anatomy directory (``DIR/lumen.stl`` plus ``DIR/lumen.yaml``, as
            ``prepare_anatomy`` writes), a mesh file
            (:data:`MESH_SUFFIXES`, millimetres) with its ``<stem>.yaml`` landmarks, or an
            :class:`Anatomy` (returned as is).

    Returns:
        The anatomy, named :func:`anatomy_label`. Built-in anatomies are cached as
        :func:`build_anatomy` caches them; a path is loaded once per process and file state
        (its resolved path and the modification time and size of the mesh and the landmarks),
        so an edited file is read again.

    Raises:
        AnatomyError: one line naming the argument or the path and what was wrong: not a name
            and no such path, a directory that is not a prepared anatomy, a file of another
            type, missing landmarks, or a mesh that fails to load
            (:class:`~cgail_sim.mesh_io.MeshLoadError`).
    """
    if isinstance(spec, Anatomy):
        return spec
    if is_builtin(spec):
        return build_anatomy(str(spec))
    if (seed := _population_seed(spec)) is not None:
        return population.sample_anatomy(seed)
    check_anatomy_spec(spec)
    real = real_anatomy_dir(spec)
    mesh = _mesh_of(spec if real is None else real).resolve()
    sidecar = mesh.with_suffix(".yaml")
    stats = [f.stat() for f in (mesh, sidecar)]
    key = (str(mesh), (stats[0].st_mtime_ns, stats[0].st_size),
           (stats[1].st_mtime_ns, stats[1].st_size))
    anatomy = _PATH_CACHE.get(key)
    if anatomy is None:
        try:
            anatomy = load_anatomy_mesh(mesh, name=anatomy_label(spec))
        except AnatomyError as exc:
            text = str(exc)
            if str(mesh) not in text and str(sidecar) not in text:
                text = f"anatomy {mesh}: {text}"
            raise type(exc)(text) from None
        if len(_PATH_CACHE) >= _PATH_CACHE_MAX:
            _PATH_CACHE.pop(next(iter(_PATH_CACHE)))
        _PATH_CACHE[key] = anatomy
    return anatomy
