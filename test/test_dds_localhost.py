"""A node started through the normal path talks to another over DDS, on localhost only.

The normal path: the launcher starts ``install/catheter_driver/lib/catheter_driver/teleop_node``
(the executable ``ros2 run`` would start) as a child process with the environment of
``scripts/env.sh``. This test process is the other DDS participant: it publishes
``sensor_msgs/Joy`` with the deadman held and must receive the teleop node's insertion
command. Then it checks that discovery stayed on this machine: the child runs with
``ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`` and has no socket on the domain's multicast
discovery port (7400 + 250 * domain id), which Fast DDS opens only when it multicasts.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
import subprocess
import time

import pytest

from cgail_rig.launch_spec import parse_launch
from cgail_rig.launcher import ProcessLauncher


def _udp_ports_of(pid: int) -> set[int]:
    out = subprocess.run(['ss', '-uanp'], capture_output=True, text=True, check=True).stdout
    ports = set()
    for line in out.splitlines():
        if f'pid={pid},' in line:
            local = line.split()[3]
            ports.add(int(local.rsplit(':', 1)[1]))
    return ports


def _environ_of(pid: int) -> dict[str, str]:
    raw = Path(f'/proc/{pid}/environ').read_bytes().split(b'\0')
    return dict(kv.decode().split('=', 1) for kv in raw if b'=' in kv)


def test_teleop_child_talks_over_localhost_dds(rclpy_context, tmp_path):
    rclpy = rclpy_context
    from sensor_msgs.msg import JointState, Joy

    domain = int(os.environ.get('ROS_DOMAIN_ID', '0'))
    spec = parse_launch({'launch': [{'node': {
        'name': 'teleop', 'pkg': 'catheter_driver', 'exec': 'teleop_node',
        'param': [{'name': 'enable_button', 'value': 4}, {'name': 'axis_insertion', 'value': 1},
                  {'name': 'scale_insertion', 'value': 0.004}],
        # as the rig's launch files: the node's own names onto the rig's (-r on its command line)
        'remap': [{'from': '~/joy', 'to': 'joy'},
                  {'from': '~/insertion_command', 'to': 'catheter/insertion_command'}],
    }}]}, tmp_path, name='dds')
    log = io.StringIO()
    launcher = ProcessLauncher(spec, out=log, shutdown_timeout=5.0)
    launcher.start()
    node = rclpy.create_node('dds_probe')
    try:
        got: list[JointState] = []
        node.create_subscription(JointState, 'catheter/insertion_command', got.append, 10)
        pub = node.create_publisher(Joy, 'joy', 10)
        joy = Joy()
        joy.axes = [0.0, 1.0, 0.0, 0.0, 0.0, 0.0]
        joy.buttons = [0, 0, 0, 0, 1, 0, 0, 0]
        deadline = time.monotonic() + 30.0
        while not got and time.monotonic() < deadline:
            joy.header.stamp = node.get_clock().now().to_msg()
            pub.publish(joy)
            rclpy.spin_once(node, timeout_sec=0.05)
        assert got, f'no insertion command from the teleop child; its log:\n{log.getvalue()}'
        msg = got[-1]
        assert list(msg.name) == ['insertion']
        assert msg.velocity[0] == pytest.approx(0.004)

        pid = launcher.pids()['teleop']
        env = _environ_of(pid)
        assert env.get('ROS_AUTOMATIC_DISCOVERY_RANGE') == 'LOCALHOST'
        assert env.get('ROS_DOMAIN_ID') == str(domain)
        multicast_discovery_port = 7400 + 250 * domain
        ports = _udp_ports_of(pid)
        assert ports, 'the child has no UDP sockets at all: is it a DDS participant?'
        assert multicast_discovery_port not in ports, \
            f'child listens on the multicast discovery port {multicast_discovery_port}'
    finally:
        node.destroy_node()
        launcher.request_stop()
        launcher.shutdown()
    assert 'sending SIGINT to teleop' in log.getvalue()
