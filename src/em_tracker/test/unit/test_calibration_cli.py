"""``register_phantom`` and ``pivot_calibrate``: files in, a parameters file out, exit codes."""

from __future__ import annotations

from pathlib import Path
import re

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from synthetic_phantom import (
    apply_transform,
    fiducials,
    hidden_offset,
    hidden_transform,
    PIVOT,
    pivoting,
    pose_errors,
    touch,
    traced,
    tube_mesh,
)
import yaml

from em_tracker.cli import pivot_calibrate, register_phantom
from em_tracker.core.config import TrackerConfig
from em_tracker.core.pose import Registration

HEADER = 'name,model_x_mm,model_y_mm,model_z_mm,tracker_x_mm,tracker_y_mm,tracker_z_mm'


def write_fiducials(path: Path, model_m: np.ndarray, tracker_m: np.ndarray) -> Path:
    rows = [f'F{i + 1},' + ','.join(f'{v * 1e3:.4f}' for v in (*m, *t))
            for i, (m, t) in enumerate(zip(model_m, tracker_m, strict=True))]
    path.write_text('# touched with the pointer, 2025-01-01\n' + '\n'.join([HEADER, *rows])
                    + '\n')
    return path


def params(path: Path) -> dict:
    return yaml.safe_load(path.read_text())['aurora']['ros__parameters']


@pytest.fixture
def scene(tmp_path):
    rng = np.random.default_rng(0)
    truth = hidden_transform(rng)
    model = fiducials(rng, 7)
    return truth, write_fiducials(tmp_path / 'fid.csv', model, touch(model, truth, rng))


def test_register_round_trip_is_read_by_the_node_config(scene, tmp_path, capsys):
    truth, fid = scene
    out = tmp_path / 'calibration.yaml'
    assert register_phantom.main([str(fid), '-o', str(out)]) == 0
    assert 'FRE' in capsys.readouterr().out
    reg = Registration.from_flat(params(out)['registration'])  # what aurora_node does
    pos_err, ang_err = pose_errors(reg.matrix, truth, np.zeros((1, 3)))
    assert pos_err < 1e-3 and ang_err < 1.0
    assert TrackerConfig(registration=reg).registration is reg
    # rcl's own parser reads it as the double array the node declares
    from rcl_interfaces.msg import ParameterType
    from rclpy.parameter import parameter_dict_from_yaml_file
    parsed = parameter_dict_from_yaml_file(str(out), target_nodes=['aurora'])
    assert parsed['registration'].value.type == ParameterType.PARAMETER_DOUBLE_ARRAY


def test_register_with_icp_from_a_mesh_file(tmp_path, capsys):
    trimesh = pytest.importorskip('trimesh')
    rng = np.random.default_rng(4)
    truth = hidden_transform(rng)
    model = fiducials(rng, 6)
    fid = write_fiducials(tmp_path / 'fid.csv', model, touch(model, truth, rng))
    verts, faces = tube_mesh()
    trimesh.Trimesh(verts * 1e3, faces, process=False).export(tmp_path / 'lumen.stl')
    on_wall = traced(rng)
    traj = tmp_path / 'traced.csv'
    np.savetxt(traj, touch(on_wall, truth, rng) * 1e3, delimiter=',', header='x_mm,y_mm,z_mm',
               comments='')
    out = tmp_path / 'calibration.yaml'
    assert register_phantom.main([str(fid), '-o', str(out), '--trajectory', str(traj),
                                  '--mesh', str(tmp_path / 'lumen.stl')]) == 0
    assert 'ICP: 200 points' in capsys.readouterr().out
    reg = Registration.from_flat(params(out)['registration'])
    pos_err, ang_err = pose_errors(reg.matrix, truth, on_wall)
    assert pos_err < 1e-3 and ang_err < 1.0


def test_register_yaml_fiducials_and_npz_surface(tmp_path):
    rng = np.random.default_rng(6)
    truth = hidden_transform(rng)
    model = fiducials(rng, 6)
    tracker = touch(model, truth, rng)
    fid = tmp_path / 'fid.yaml'
    fid.write_text(yaml.safe_dump({'unit': 'm', 'fiducials': [
        {'name': f'F{i}', 'model': m.tolist(), 'tracker': t.tolist()}
        for i, (m, t) in enumerate(zip(model, tracker, strict=True))]}))
    verts, faces = tube_mesh()
    np.savez(tmp_path / 'lumen.npz', vertices=verts, faces=faces)
    traj = tmp_path / 'traced.csv'
    np.savetxt(traj, touch(traced(rng), truth, rng), delimiter=',', header='x_m,y_m,z_m',
               comments='')
    out = tmp_path / 'calibration.yaml'
    assert register_phantom.main([str(fid), '-o', str(out), '--trajectory', str(traj),
                                  '--mesh', str(tmp_path / 'lumen.npz'), '--mesh-unit',
                                  'm']) == 0
    reg = Registration.from_flat(params(out)['registration'])
    assert pose_errors(reg.matrix, truth, np.zeros((1, 3)))[0] < 1e-3


@pytest.mark.parametrize('content,match', [
    (None, 'no such file'),
    ('a,b,c\n1,2,3\n', 'expected columns model_x_mm model_y_mm model_z_mm'),
    (HEADER + '\nF1,1,2,3,4,5\n', 'data row 2 has 6 fields, expected 7'),
    (HEADER + '\nF1,1,2,3,4,5,nan\n', 'column tracker_z_mm: expected a finite number'),
    (HEADER + '\nF1,1,2,3,4,5,x\n', "column tracker_z_mm: expected a number, found 'x'"),
    (HEADER + '\n' + '\n'.join(f'F{i},{10 * i},0,0,{10 * i},0,0' for i in range(5)),
     r'fiducials \(nearly\) collinear'),
    (HEADER + '\n', 'expected data rows after the header'),
])
def test_register_bad_input_exits_2_and_keeps_the_output(tmp_path, capsys, content, match):
    fid = tmp_path / 'fid.csv'
    if content is not None:
        fid.write_text(content)
    out = tmp_path / 'calibration.yaml'
    out.write_text('aurora:\n  ros__parameters:\n    port: /dev/ttyUSB1\n')
    before = out.read_text()
    assert register_phantom.main([str(fid), '-o', str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and err.startswith('register_phantom: error: ')
    assert re.search(match, err), err
    assert out.read_text() == before


def test_register_refuses_a_high_fre_unless_forced(tmp_path, capsys):
    rng = np.random.default_rng(3)
    truth = hidden_transform(rng)
    model = fiducials(rng, 6)
    tracker = touch(model, truth, rng)
    tracker[2] += [0.01, 0.0, 0.0]
    fid = write_fiducials(tmp_path / 'fid.csv', model, tracker)
    out = tmp_path / 'calibration.yaml'
    assert register_phantom.main([str(fid), '-o', str(out)]) == 1
    assert 'refused: FRE' in capsys.readouterr().err and not out.exists()
    assert register_phantom.main([str(fid), '-o', str(out), '--force']) == 0
    assert out.exists()


def test_register_refuses_a_malformed_output_file(scene, tmp_path):
    _, fid = scene
    out = tmp_path / 'calibration.yaml'
    out.write_text('- just\n- a list\n')
    assert register_phantom.main([str(fid), '-o', str(out)]) == 2
    assert out.read_text() == '- just\n- a list\n'


def pose_rows(rot: np.ndarray, pos_m: np.ndarray) -> list[str]:
    quat = Rotation.from_matrix(rot).as_quat()
    return [f'{k * 0.025:.3f},' + ','.join(f'{v:.6f}' for v in (*p * 1e3, *q))
            for k, (p, q) in enumerate(zip(pos_m, quat, strict=True))]


def test_pivot_round_trip_shares_the_file_with_the_registration(scene, tmp_path, capsys):
    _, fid = scene
    rng = np.random.default_rng(2)
    offset = hidden_offset(rng)
    poses = tmp_path / 'pivot.csv'
    poses.write_text('\n'.join(['t_s,x_mm,y_mm,z_mm,qx,qy,qz,qw',
                                *pose_rows(*pivoting(rng, offset, 40, tilt_deg=30.0))]) + '\n')
    out = tmp_path / 'calibration.yaml'
    assert register_phantom.main([str(fid), '-o', str(out)]) == 0
    assert pivot_calibrate.main([str(poses), '-o', str(out)]) == 0
    assert 'residual RMS' in capsys.readouterr().out
    values = params(out)
    tool = Registration.from_flat(values['tool_transform']).matrix
    assert np.linalg.norm(tool[:3, 3] - offset) < 1e-3
    assert tool[:3, 1] @ offset / np.linalg.norm(offset) > np.cos(np.radians(5.0))
    Registration.from_flat(values['registration'])  # kept
    text = out.read_text()
    assert '# register_phantom: ' in text and '# pivot_calibrate: ' in text
    # an explicit shaft axis is used as given
    assert pivot_calibrate.main([str(poses), '-o', str(out), '--shaft-axis', '0,0,1']) == 0
    tool = Registration.from_flat(params(out)['tool_transform']).matrix
    assert tool[:3, 1] == pytest.approx([0.0, 0.0, 1.0], abs=1e-9)


def test_pivot_from_a_bag(tmp_path):
    pytest.importorskip('rosbags')
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import get_typestore, Stores
    store = get_typestore(Stores.ROS2_JAZZY)
    pose_t = store.types['geometry_msgs/msg/PoseStamped']
    header_t, stamp_t = store.types['std_msgs/msg/Header'], store.types[
        'builtin_interfaces/msg/Time']
    pose_msg, point_t, quat_t = (store.types['geometry_msgs/msg/Pose'],
                                 store.types['geometry_msgs/msg/Point'],
                                 store.types['geometry_msgs/msg/Quaternion'])
    rng = np.random.default_rng(8)
    offset = hidden_offset(rng)
    rot, pos = pivoting(rng, offset, 40, tilt_deg=25.0)
    bag = tmp_path / 'pivot_bag'
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conn = writer.add_connection('/em_tracker/tip_pose', pose_t.__msgtype__,
                                     typestore=store)
        for k, (r, p) in enumerate(zip(rot, pos, strict=True)):
            q = Rotation.from_matrix(r).as_quat()
            msg = pose_t(header=header_t(stamp=stamp_t(sec=k, nanosec=0), frame_id='phantom'),
                         pose=pose_msg(position=point_t(x=p[0], y=p[1], z=p[2]),
                                       orientation=quat_t(x=q[0], y=q[1], z=q[2], w=q[3])))
            writer.write(conn, k * 25_000_000, store.serialize_cdr(msg, pose_t.__msgtype__))
    out = tmp_path / 'calibration.yaml'
    assert pivot_calibrate.main([str(bag), '-o', str(out)]) == 0
    tool = Registration.from_flat(params(out)['tool_transform']).matrix
    assert np.linalg.norm(tool[:3, 3] - offset) < 1e-3
    # the pivot point itself is not written, but the tip lands on it
    tip = apply_transform(np.block([[rot[0], pos[0][:, None]], [np.zeros((1, 3)), 1.0]]),
                          tool[None, :3, 3])[0]
    assert np.linalg.norm(tip - PIVOT) < 2e-3
    assert pivot_calibrate.main([str(bag), '-o', str(out), '--topic', 'other/pose']) == 2


@pytest.mark.parametrize('rows,match', [
    (['x_mm,y_mm,z_mm,qx,qy,qz', '1,2,3,0,0,0'], 'missing qw'),
    (['x_mm,y_mm,z_mm,qx,qy,qz,qw', '1,2,3,0,0,0,2'], 'expected a unit quaternion'),
    (['x_mm,y_mm,z_mm,qx,qy,qz,qw', '1,2,nan,0,0,0,1'], 'expected a finite number'),
    (None, 'too little'),
])
def test_pivot_bad_input_exits_2(tmp_path, capsys, rows, match):
    poses = tmp_path / 'pivot.csv'
    if rows is None:  # barely pivoted
        rng = np.random.default_rng(0)
        rows = ['t_s,x_mm,y_mm,z_mm,qx,qy,qz,qw',
                *pose_rows(*pivoting(rng, hidden_offset(rng), 40, tilt_deg=1.0))]
    poses.write_text('\n'.join(rows) + '\n')
    out = tmp_path / 'calibration.yaml'
    assert pivot_calibrate.main([str(poses), '-o', str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count('\n') == 1 and match in err, err
    assert not out.exists()
