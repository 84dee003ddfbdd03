"""sim_render: PNG output of the anatomy with overlays (small, fast renders)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cgail_sim.anatomy import build_anatomy
from cgail_sim.centerline import compute_centerlines
from cgail_sim.render import heartbeat_phases, main, render_anatomy

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _is_png(path: Path, min_bytes: int = 5000) -> bool:
    data = path.read_bytes()
    return data[:8] == PNG_MAGIC and len(data) > min_bytes


def test_render_anatomy_writes_png_with_overlays(tmp_path: Path) -> None:
    anatomy = build_anatomy("default")
    lines = compute_centerlines(anatomy)
    rollout = lines["left"].points[::10]
    out = render_anatomy(anatomy, tmp_path / "sub" / "a.png", centerlines=lines,
                         rollout=rollout, scenarios=False, views=("anterior", "root"), dpi=40)
    assert out == tmp_path / "sub" / "a.png"
    assert _is_png(out)


def test_render_rejects_unknown_view(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="views must be from"):
        render_anatomy(build_anatomy("default"), tmp_path / "x.png", views=("top",))


def test_cli_main_with_rollout(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rollout = tmp_path / "tips.npy"
    np.save(rollout, build_anatomy("default").start_point[None] + np.zeros((5, 3)))
    out = tmp_path / "cli.png"
    rc = main(["--anatomy", "default", "--out", str(out), "--rollout", str(rollout),
               "--no-scenarios", "--dpi", "30"])
    assert rc == 0
    assert capsys.readouterr().out.strip() == str(out)
    assert _is_png(out)


def test_cli_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.npy"
    np.save(bad, np.zeros((4, 2)))
    assert main(["--out", str(tmp_path / "b.png"), "--rollout", str(bad), "--dpi", "30"]) == 2
    assert "rollout must be a (T, 3) array" in capsys.readouterr().err
    assert main(["--anatomy", str(tmp_path / "nope.stl"), "--out", str(tmp_path / "c.png")]) == 2
    assert "nope.stl': no such file or directory" in capsys.readouterr().err


def test_heartbeat_phases_move_the_root() -> None:
    anatomy = build_anatomy("default")
    phases = heartbeat_phases(anatomy, 3, dt=0.01)
    assert len(phases) == 3
    assert np.allclose(phases[0], anatomy.vertices)
    moved = np.linalg.norm(phases[1][anatomy.annulus_vertices]
                           - anatomy.vertices[anatomy.annulus_vertices], axis=1)
    assert moved.max() > 1e-3
    with pytest.raises(ValueError, match="n_phases must be >= 1"):
        heartbeat_phases(anatomy, 0)


def test_cli_population_grid(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "grid.png"
    assert main(["--population", "1", "--seed", "0", "--out", str(out), "--dpi", "30"]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    assert _is_png(out, min_bytes=2000)
    assert main(["--population", "2", "--seed", "-1", "--out", str(out)]) == 2
    assert "population and seed must be >= 0, found 2 and -1" in capsys.readouterr().err
