"""cgail_gui.core.igtl: the phantom -> CT (RAS mm) mapping, read from prepare_anatomy's
record and never recomputed; cell arrays; the wall from the lumen marker; the config."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
import yaml

from cgail_gui.core import igtl
from cgail_gui.core.igtl import CtFrameError

LPS_FROM_RAS = np.diag([-1.0, -1.0, 1.0])


def record(frame: str = 'RAS', r=None, t=(10.5, -20.25, 300.0), content_hash='abc') -> dict:
    """A prepare.yaml record as prepare_anatomy writes it (only what the bridge reads)."""
    r = (LPS_FROM_RAS if frame == 'RAS' else np.eye(3)) if r is None else r
    return {'name': 'p07',
            'frame_conversion': {'input_frame': frame, 'phantom_from_input': igtl.PREPARE_FORMULA,
                                 'R': np.asarray(r).tolist(), 't_input_mm': list(t)},
            'anatomy': {'vertices': 2455, 'faces': 4906, 'content_hash': content_hash}}


def test_an_anatomy_without_ct_is_the_phantom_in_mm_with_ras_axes() -> None:
    frame = igtl.phantom_ct_frame()
    assert frame.matrix.tolist() == np.diag([-1000.0, -1000.0, 1000.0, 1.0]).tolist()
    assert frame.points_mm(np.array([[0.01, 0.02, -0.03]])).tolist() == [[-10.0, -20.0, -30.0]]
    assert frame.points_mm(np.array([0.0, 0.0, 0.0])).tolist() == [0.0, 0.0, 0.0]


def test_nifti_record_gives_the_scanner_ras_frame() -> None:
    # p_phantom = R (p_input - t) / 1000 with R = LPS_FROM_RAS: p_input = R^-1 (1000 p) + t
    frame = igtl.ct_frame_from_record(record('RAS'))
    assert frame.points_mm(np.array([0.01, 0.02, 0.03])).tolist() == [0.5, -40.25, 330.0]
    assert frame.rotation.tolist() == LPS_FROM_RAS.tolist()
    assert frame.translation_mm.tolist() == [10.5, -20.25, 300.0]
    assert 'input frame RAS' in frame.source


def test_lps_mesh_record_is_turned_to_ras() -> None:
    frame = igtl.ct_frame_from_record(record('LPS', t=(1.0, 2.0, 3.0)))
    # LPS input (11, 22, 33) mm is RAS (-11, -22, 33)
    assert frame.points_mm(np.array([0.01, 0.02, 0.03])).tolist() == [-11.0, -22.0, 33.0]


def test_record_is_inverted_as_written_for_any_rotation() -> None:
    r = Rotation.from_euler('zyx', [30.0, -12.0, 5.0], degrees=True).as_matrix()
    t = np.array([-101.5, 37.25, 1203.0])
    frame = igtl.ct_frame_from_record(record('RAS', r=r, t=t))
    p = np.array([[0.012, -0.034, 0.056], [0.0, 0.0, 0.0]])
    back = (r @ (frame.points_mm(p) - t).T).T / 1000.0  # prepare.yaml's formula
    assert float(np.abs(back - p).max()) < 1e-12


def test_pose_maps_rotation_and_position() -> None:
    frame = igtl.ct_frame_from_record(record('RAS'))
    rot = Rotation.from_euler('xyz', [10.0, 20.0, 30.0], degrees=True).as_matrix()
    pose = frame.pose_mm(np.array([0.01, 0.02, 0.03]), rot)
    assert pose[:3, :3] == pytest.approx(LPS_FROM_RAS @ rot, abs=1e-15)
    assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)
    assert pose[:3, 3].tolist() == [0.5, -40.25, 330.0]
    assert pose[3].tolist() == [0.0, 0.0, 0.0, 1.0]


@pytest.mark.parametrize(('change', 'match'), [
    (lambda r: r.pop('frame_conversion'), 'expected a frame_conversion mapping'),
    (lambda r: r['frame_conversion'].update(phantom_from_input='p = R p'),
     'expected frame_conversion.phantom_from_input'),
    (lambda r: r['frame_conversion'].update(input_frame='RAI'),
     "input_frame RAS or LPS in prepare.yaml, found 'RAI'"),
    (lambda r: r['frame_conversion'].update(R=[[1, 0], [0, 1]]),
     r'expected frame_conversion.R of shape \(3, 3\)'),
    (lambda r: r['frame_conversion'].update(t_input_mm=[0.0, float('nan'), 1.0]),
     r'expected frame_conversion.t_input_mm of shape \(3,\)'),
    (lambda r: r['frame_conversion'].update(R=np.diag([1.0, 1.0, -1.0]).tolist()),
     'expected rotation to be a proper 3x3 rotation'),
    (lambda r: r['anatomy'].update(content_hash='0123'),
     "content hash abc\\), found content hash '0123': the lumen changed"),
])
def test_unusable_records_are_refused(change, match: str) -> None:
    r = record('RAS')
    change(r)
    with pytest.raises(CtFrameError, match=match):
        igtl.ct_frame_from_record(r, content_hash='abc')


def test_ct_frame_of_names_paths_and_records(tmp_path: Path) -> None:
    assert 'built-in anatomy default' in igtl.ct_frame_of('default').source
    assert igtl.ct_frame_of('population-3').matrix.tolist() == \
        igtl.phantom_ct_frame().matrix.tolist()
    d = tmp_path / 'p07'
    d.mkdir()
    assert igtl.prepare_record_path(d) is None
    assert 'no prepare.yaml beside' in igtl.ct_frame_of(d).source
    (d / 'prepare.yaml').write_text(yaml.safe_dump(record('RAS')))
    for spec in (d, str(d), d / 'lumen.stl'):
        assert igtl.prepare_record_path(spec) == d / 'prepare.yaml'
        frame = igtl.ct_frame_of(spec, content_hash='abc')
        assert frame.translation_mm.tolist() == [10.5, -20.25, 300.0]
        assert str(d / 'prepare.yaml') in frame.source
    assert igtl.prepare_record_path(d / 'other.stl') is None
    (d / 'prepare.yaml').write_text('frame_conversion: [unclosed\n')
    with pytest.raises(CtFrameError, match='expected a readable YAML record in'):
        igtl.ct_frame_of(d)
    (d / 'prepare.yaml').write_text('- a list\n')
    with pytest.raises(CtFrameError, match=r'expected a mapping in .*, found list'):
        igtl.ct_frame_of(d)


def test_cell_arrays() -> None:
    assert igtl.polygon_cells(np.array([[0, 1, 2], [2, 3, 4]])).tolist() == \
        [3, 0, 1, 2, 3, 2, 3, 4]
    assert igtl.polygon_cells(np.array([[0, 1, 2]])).dtype == np.uint32
    assert igtl.line_cells(4).tolist() == [4, 0, 1, 2, 3]
    assert igtl.line_cells(1).tolist() == []


def test_wall_from_the_lumen_marker() -> None:
    rest = np.arange(15, dtype=float).reshape(5, 3) * 1e-3
    wall_faces = np.array([[0, 1, 2], [1, 2, 3]])  # vertex 4: inside a cap
    moved = rest + 0.002
    got = igtl.wall_from_triangles(rest, wall_faces, moved[wall_faces.reshape(-1)])
    assert got is not None
    assert got[:4].tolist() == moved[:4].tolist()
    assert got[4].tolist() == rest[4].tolist()
    assert igtl.wall_from_triangles(rest, wall_faces, moved[:3]) is None  # another count
    far = rest + igtl.MAX_WALL_DISPLACEMENT * 1.5
    assert igtl.wall_from_triangles(rest, wall_faces, far[wall_faces.reshape(-1)]) is None


@pytest.mark.parametrize(('kwargs', 'match'), [
    (dict(host='my-laptop'), "host must be an IPv4 or IPv6 address or 'localhost', found"),
    (dict(host=''), 'host must be'),
    (dict(port=65536), r'port must be an int in \[0, 65535\], found 65536'),
    (dict(port=True), 'port must be an int'),
    (dict(tip_rate_hz=0.5), r'tip_rate_hz must be in \[1, 200\], found 0.5'),
    (dict(tip_rate_hz=float('nan')), 'tip_rate_hz must be in'),
])
def test_config_refuses_bad_values(kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        igtl.IgtlBridgeConfig(**kwargs)


def test_config_defaults() -> None:
    c = igtl.IgtlBridgeConfig()
    assert (c.host, c.port, c.tip_rate_hz, c.follow_wall) == ('127.0.0.1', 18944, 20.0, True)
    assert igtl.IgtlBridgeConfig(host='::1', port=0).port == 0
    assert igtl.IgtlBridgeConfig(host='localhost').host == 'localhost'
    assert all(len(n) <= igtl.MAX_DEVICE_NAME for n in (
        igtl.TIP_DEVICE, igtl.PATH_DEVICE, igtl.TARGET_DEVICE, igtl.LUMEN_DEVICE))


@pytest.mark.slow
def test_prepared_ct_puts_the_lumen_on_the_scanner_ras_truth(tmp_path: Path) -> None:
    """prepare_anatomy on a synthetic CT label map, then the bridge's frame: the phantom's
    landmarks land on the truth in the NIfTI's scanner RAS frame, and the mapping equals
    prepare_anatomy's own (PreparedAnatomy.to_lps) to the record's rounding."""
    from cgail_patient.prepare_cli import prepare_anatomy
    from cgail_patient.synthetic import make_synthetic_ct, SyntheticCTConfig

    ct = make_synthetic_ct(SyntheticCTConfig(spacing_mm=(1.6, 1.6, 2.0),
                                             descending_length_mm=170.0))
    paths = ct.write(tmp_path)
    result = prepare_anatomy([str(paths['aorta']), '--lv', str(paths['lv']), '--out',
                              str(tmp_path / 'p'), '--voxel-mm', '1.2', '--target-vertices',
                              '1500', '--no-wall-check', '--no-expert-check'])
    assert result.usable
    frame = igtl.ct_frame_of(tmp_path / 'p', result.anatomy.content_hash)
    a = result.anatomy
    points = np.array([a.annulus_center, a.ostia['left'], a.ostia['right']])
    expected = result.prepared.to_lps(points) @ LPS_FROM_RAS.T
    assert frame.points_mm(points) == pytest.approx(expected, abs=1e-3)
    truth = ct.truth.landmarks
    assert np.linalg.norm(frame.points_mm(a.annulus_center) - truth['annulus_center']) < 2.0
    for side in ('left', 'right'):
        assert np.linalg.norm(frame.points_mm(a.ostia[side]) - truth[f'{side}_ostium']) < 3.0
