"""``aurora_node``: NDI Aurora tip pose -> ``~/tip_pose`` (node name ``aurora``).

Topics are the node's own (``~/tip_pose``, ``~/tip_pose_cov``, ``~/rms_error``: under its
name); the rig's launch files remap them to ``em_tracker/...`` (docs/interfaces.md).

The published pose is the catheter tip's in the ``phantom`` frame (``frame_id``):
``T_phantom_aurora @ T_aurora_sensor @ T_sensor_tip``, with the ``registration`` (aurora ->
phantom, from ``register_phantom``) and the ``tool_transform`` (sensor -> tip, from
``pivot_calibrate``) parameters. Tip frame: origin at the tip, **+y along the shaft towards the
tip** (the catheter heading), x/z the sensor's turned onto the shaft (roll not calibrated; see
:mod:`em_tracker.core.calibration`). With the default identity ``tool_transform`` the pose is the
sensor's. ``~/tip_pose_cov`` carries the same pose with a covariance from the
reported RMS error (position variance ``rms^2 / 3`` per axis; orientation not estimated, see
:func:`em_tracker.core.pose.pose_covariance`).

TF (``publish_tf``, default on): the node owns the registration and the tip, so it publishes
both: ``aurora -> phantom`` (``tracker_frame_id -> frame_id``, the inverse of the registration)
on ``/tf_static`` (transient local, so a late tf listener or recorder gets it) at every
configure, and ``phantom -> catheter_tip`` (``frame_id -> tip_frame_id``) on ``/tf`` with every
published pose, with the pose's stamp. The messages are ``tf2_msgs/msg/TFMessage`` from the
workspace's interface package (``src/interfaces/tf2_msgs``).

A lifecycle node (``rclpy.lifecycle.LifecycleNode``; ``main`` configures and activates it
unless ``autostart`` is false, which leaves it unconfigured for a lifecycle manager):

* constructor: parameters declared and validated into a :class:`TrackerConfig` (bad values
  raise ``ValueError`` here);
* ``on_configure``: the parameters are read again into :attr:`AuroraNode.config`, the device
  object (ndicapi, or its isolating child process) is built, the lifecycle publishers, the pose
  guard condition and the diagnostics timer are created;
* ``on_activate``: a fresh reader thread starts (INIT ... TSTART, then polling); poses and
  ``/diagnostics`` are published only while active;
* ``on_deactivate``: the reader thread is stopped and joined (TSTOP, port closed on it);
* ``on_cleanup``: publishers, timer, guard condition and the device are released;
* ``on_shutdown`` / ``on_error`` / ``destroy_node``: stop the reader (TSTOP) and release, in
  any state.

Parameters are read at configure: a change is accepted only while the node is unconfigured
(validated, applied by the next configure); in any other state ``set_parameters`` answers
``successful=False`` with the reason (:mod:`cgail_node_utils.parameters`). ``autostart`` is
read-only.

The link (:class:`~em_tracker.hw.tracker_loop.TrackerLoop`) runs the start-up sequence, polls
at the device frame rate, validates and converts, and reconnects with exponential backoff. With
``poll_mode: thread`` (default, a real rig) a reader thread owns every blocking serial call and
hands poses to the executor through a deque and a guard condition. With ``poll_mode: clock``
(the lockstep simulated rig) a timer of the node clock polls once per frame period and
publishes in the same callback, stamped with the node clock: the poses are then a function of
simulated time only. The link state is published on ``/diagnostics``.
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Mapping
import threading
import time
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, TransformStamped
import rclpy
from rclpy.guard_condition import GuardCondition
from rclpy.lifecycle import LifecycleNode, LifecyclePublisher, State, TransitionCallbackReturn
from rclpy.qos import DurabilityPolicy, qos_profile_sensor_data, QoSProfile, ReliabilityPolicy
from rclpy.timer import Timer
from std_msgs.msg import Float64
from tf2_msgs.msg import TFMessage

from cgail_node_utils.entry_point import run_node, start_lifecycle
from cgail_node_utils.parameters import AUTOSTART_DESCRIPTION, configure_time_guard, descriptor
from em_tracker.core.config import TrackerConfig
from em_tracker.core.pose import Registration, TipPose
from em_tracker.core.tracking import TrackerHealth
from em_tracker.hw.aurora import (
    AuroraDevice,
    AuroraSettings,
    InProcessAurora,
    IsolatedAurora,
    NdiAurora,
)
from em_tracker.hw.tracker_loop import TrackerLoop
from em_tracker.nodes.conversions import (
    diagnostic_status,
    registration_tf,
    tip_pose_to_cov_msg,
    tip_pose_to_msg,
    tip_tf,
)

DeviceFactory = Callable[[TrackerConfig], AuroraDevice]

_DEFAULTS = TrackerConfig()
# name -> (default, description, range (low, high) or None)
_PARAMS: dict[str, tuple[object, str, tuple[float, float] | None]] = {
    'port': (_DEFAULTS.port, 'serial device of the Aurora (or a sim_aurora pty/symlink)', None),
    'baud': (_DEFAULTS.baud, 'baud rate set with COMM after INIT (9600..230400)', None),
    'tool_handle': (_DEFAULTS.tool_handle, 'port handle to publish; 0 = first enabled', (0, 255)),
    'priority': (_DEFAULTS.priority, 'PENA tracking priority: D, S or B', None),
    'srom_files': ('', "comma-separated 'hh:/path/tool.rom' SROM images written with PVWR",
                   None),
    'use_bx': (_DEFAULTS.use_bx, 'poll with binary BX:0001 instead of TX:0001', None),
    'rate_hz': (_DEFAULTS.rate_hz, 'device frame rate followed by the poller, Hz', (1.0, 1000.0)),
    'registration': ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                     'aurora->phantom: 7 values [tx ty tz qx qy qz qw] (m) or 16 (4x4 row-major)',
                     None),
    'tool_transform': ([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                       'sensor->tip: 7 values [tx ty tz qx qy qz qw] (m) or 16 (4x4 row-major); '
                       'tip frame: origin at the tip, +y along the shaft towards the tip', None),
    'frame_id': (_DEFAULTS.frame_id, 'frame_id of the published pose', None),
    'tracker_frame_id': (_DEFAULTS.tracker_frame_id, "the field generator's frame: parent of "
                         'frame_id on /tf_static', None),
    'tip_frame_id': (_DEFAULTS.tip_frame_id, 'the tip frame: child of frame_id on /tf', None),
    'publish_tf': (_DEFAULTS.publish_tf, 'publish tracker_frame_id -> frame_id on /tf_static and '
                   'frame_id -> tip_frame_id on /tf', None),
    'max_abs_position_m': (_DEFAULTS.max_abs_position_m,
                           'reject readings with a coordinate beyond this, m', (0.01, 10.0)),
    'reply_timeout_s': (_DEFAULTS.reply_timeout_s, 'longest wait for a reply, s', (0.1, 60.0)),
    'max_consecutive_errors': (_DEFAULTS.max_consecutive_errors,
                               'bad replies in a row before reconnecting', (1, 1000)),
    'reconnect_initial_s': (_DEFAULTS.reconnect_initial_s, 'first reconnect delay, s',
                            (0.01, 60.0)),
    'reconnect_max_s': (_DEFAULTS.reconnect_max_s, 'max reconnect delay, s', (0.01, 600.0)),
    'stale_after_s': (_DEFAULTS.stale_after_s, 'diagnostics STALE after this long without a '
                      'new frame, s', (0.01, 60.0)),
    'diagnostics_period_s': (_DEFAULTS.diagnostics_period_s, '/diagnostics period, s',
                             (0.05, 60.0)),
    'isolate_device': (_DEFAULTS.isolate_device,
                       'run ndicapi in a child process (a crash there cannot kill the node)',
                       None),
    'poll_mode': (_DEFAULTS.poll_mode, "'thread': reader thread on the steady clock (a rig); "
                  "'clock': node-clock timer, synchronous (lockstep simulated rig)", None),
    'link': (_DEFAULTS.link, "'serial': ndicapi on port; 'in_process': the simulated Aurora "
             'of this process serving port, answered in the polling thread (TX only; the '
             'lockstep simulated session)', None),
    'autostart': (True, AUTOSTART_DESCRIPTION, None),
}
#: Parameters fixed for the node's life (the others are read at configure).
_READ_ONLY = frozenset({'autostart'})
_CONFIGURE_TIME = tuple(name for name in _PARAMS if name not in _READ_ONLY)


def build_config(values: Mapping[str, Any]) -> TrackerConfig:
    """The :class:`TrackerConfig` of the parameter values ``{name: value}``.

    Raises:
        ValueError: a value out of range or malformed.
    """
    srom = tuple(e.strip() for e in str(values['srom_files']).split(',') if e.strip())
    return TrackerConfig(
        port=values['port'], baud=values['baud'], tool_handle=values['tool_handle'],
        priority=values['priority'], srom_files=srom, use_bx=values['use_bx'],
        rate_hz=values['rate_hz'],
        registration=Registration.from_flat(list(values['registration'])),
        tool_transform=Registration.from_flat(list(values['tool_transform']),
                                              name='tool_transform'),
        frame_id=values['frame_id'], tracker_frame_id=values['tracker_frame_id'],
        tip_frame_id=values['tip_frame_id'], publish_tf=values['publish_tf'],
        max_abs_position_m=values['max_abs_position_m'],
        reply_timeout_s=values['reply_timeout_s'],
        max_consecutive_errors=values['max_consecutive_errors'],
        reconnect_initial_s=values['reconnect_initial_s'],
        reconnect_max_s=values['reconnect_max_s'], stale_after_s=values['stale_after_s'],
        diagnostics_period_s=values['diagnostics_period_s'],
        isolate_device=values['isolate_device'], poll_mode=values['poll_mode'],
        link=values['link'])


def default_device(config: TrackerConfig) -> AuroraDevice:
    """The device for ``config``: ndicapi (in a child process unless ``isolate_device`` is
    off), or the in-process link to a simulated Aurora (``link: in_process``)."""
    srom = tuple((int(h, 16), p) for h, _, p in (e.partition(':') for e in config.srom_files))
    settings = AuroraSettings(port=config.port, baud=config.baud, priority=config.priority,
                              use_bx=config.use_bx, srom_files=srom)
    if config.link == 'in_process':
        return InProcessAurora(settings)
    if config.isolate_device:
        return IsolatedAurora(settings, reply_timeout_s=config.reply_timeout_s)
    return NdiAurora(settings)


class AuroraNode(LifecycleNode):
    """Publishes the Aurora tip pose (also with a covariance), its RMS error and diagnostics.

    Args:
        device_factory: builds the device from the config (tests pass a fake).
        **kwargs: forwarded to ``LifecycleNode`` (e.g. ``parameter_overrides``).

    Raises:
        ValueError: a parameter is out of range or malformed (raised while constructing).
    """

    def __init__(self, *, device_factory: DeviceFactory | None = None, **kwargs) -> None:
        super().__init__('aurora', **kwargs)
        for name, (default, description, bounds) in _PARAMS.items():
            self.declare_parameter(name, default, descriptor(
                name, description, default=default, bounds=bounds,
                read_only=name in _READ_ONLY))
        self.autostart: bool = self.get_parameter('autostart').value
        self.config = build_config(self._parameter_values())
        self.add_on_set_parameters_callback(
            configure_time_guard(self, _CONFIGURE_TIME, build_config))
        self._device_factory: DeviceFactory = device_factory or default_device
        self._device: AuroraDevice | None = None
        self._loop: TrackerLoop | None = None
        self.health = TrackerHealth()
        self._health_lock = threading.Lock()
        self._queue: collections.deque[tuple[TipPose, float]] = collections.deque(maxlen=64)
        self._pose_pub: LifecyclePublisher | None = None
        self._cov_pub: LifecyclePublisher | None = None
        self._rms_pub: LifecyclePublisher | None = None
        self._diag_pub: LifecyclePublisher | None = None
        self._tf_pub: LifecyclePublisher | None = None
        self._tf_static_pub: Any = None
        self._guard: GuardCondition | None = None
        self._diag_timer: Timer | None = None
        self._poll_timer: Timer | None = None
        self._clocked = self.config.poll_mode == 'clock'
        # the messages of a frame, refilled for each (a publish serializes before it returns:
        # conversions.tip_pose_to_msg's ``out``)
        self._pose_msg, self._cov_msg = PoseStamped(), PoseWithCovarianceStamped()
        self._tf_msg = TFMessage(transforms=[TransformStamped()])

    # ------------------------------------------------------------------ lifecycle
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        # (valid: the guard refused any value build_config rejects)
        self.config = build_config(self._parameter_values())
        self._clocked = self.config.poll_mode == 'clock'
        # the messages of a frame, refilled for each (a publish serializes before it returns:
        # conversions.tip_pose_to_msg's ``out``)
        self._pose_msg, self._cov_msg = PoseStamped(), PoseWithCovarianceStamped()
        self._tf_msg = TFMessage(transforms=[TransformStamped()])
        self._device = self._device_factory(self.config)
        self._pose_pub = self.create_lifecycle_publisher(PoseStamped, '~/tip_pose',
                                                         qos_profile_sensor_data)
        self._cov_pub = self.create_lifecycle_publisher(
            PoseWithCovarianceStamped, '~/tip_pose_cov', qos_profile_sensor_data)
        self._rms_pub = self.create_lifecycle_publisher(Float64, '~/rms_error',
                                                        qos_profile_sensor_data)
        self._diag_pub = self.create_lifecycle_publisher(DiagnosticArray, '/diagnostics',
                                                         QoSProfile(depth=10))
        if self.config.publish_tf:
            # tf2's QoS: /tf reliable, depth 100; /tf_static reliable and transient local
            self._tf_pub = self.create_lifecycle_publisher(TFMessage, '/tf', QoSProfile(depth=100))
            self._tf_static_pub = self.create_publisher(TFMessage, '/tf_static', QoSProfile(
                depth=1, reliability=ReliabilityPolicy.RELIABLE,
                durability=DurabilityPolicy.TRANSIENT_LOCAL))
            self._tf_static_pub.publish(registration_tf(
                self.config.registration, self.get_clock().now().to_msg(),
                self.config.tracker_frame_id, self.config.frame_id))
        if self._clocked:
            self._poll_timer = self.create_timer(1.0 / self.config.rate_hz, self._on_poll_timer)
        else:
            self._guard = self.create_guard_condition(self._on_new_pose)
        self._diag_timer = self.create_timer(self.config.diagnostics_period_s,
                                             self._on_diagnostics_timer)
        self.get_logger().info(f'configured for the Aurora on {self.config.port}')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        assert self._device is not None
        self._queue.clear()
        self._loop = TrackerLoop(self._device, self.config, self._on_pose_from_reader,
                                 self._on_link_warning)
        self.health = self._loop.health
        self._health_lock = self._loop.lock
        if not self._clocked:
            self._loop.start()
        self.get_logger().info('active: tracking started')
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        self._stop_reader()
        self.get_logger().info('inactive: tracking stopped (TSTOP, port closed)')
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self._stop_reader()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self.get_logger().error(f'transition error in state {state.label}: stopping tracking')
        self._stop_reader()
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _stop_reader(self) -> None:
        """Stop and join the reader thread (TSTOP and close happen on it); idempotent."""
        loop, self._loop = self._loop, None
        if loop is not None:
            loop.stop(timeout_s=self.config.reply_timeout_s + 2.0)
        self._queue.clear()

    def _release(self) -> None:
        """Destroy the configured entities and close the device; idempotent."""
        for timer in (self._diag_timer, self._poll_timer):
            if timer is not None:
                self.destroy_timer(timer)
        self._diag_timer = self._poll_timer = None
        if self._guard is not None:
            self.destroy_guard_condition(self._guard)
            self._guard = None
        for pub in (self._pose_pub, self._cov_pub, self._rms_pub, self._diag_pub, self._tf_pub):
            if pub is not None:
                self.destroy_lifecycle_publisher(pub)
        self._pose_pub = self._cov_pub = self._rms_pub = self._diag_pub = self._tf_pub = None
        if self._tf_static_pub is not None:
            self.destroy_publisher(self._tf_static_pub)
            self._tf_static_pub = None
        device, self._device = self._device, None
        if device is not None:
            device.close()

    def _on_pose_from_reader(self, pose: TipPose, host_time: float) -> None:
        # Reader thread: hand over to the executor (deque append and trigger are thread-safe).
        self._queue.append((pose, host_time))
        guard = self._guard
        if guard is not None:
            guard.trigger()

    def _on_link_warning(self, message: str) -> None:
        self.get_logger().warning(message, throttle_duration_sec=5.0)

    def _parameter_values(self) -> dict[str, Any]:
        return {name: self.get_parameter(name).value for name in _CONFIGURE_TIME}

    # ------------------------------------------------------------------ executor callbacks
    def _now(self) -> float:
        """Seconds on the clock the link runs on: the node clock in clock mode, else steady."""
        if self._clocked:
            return self.get_clock().now().nanoseconds * 1e-9
        return time.monotonic()

    def _on_poll_timer(self) -> None:
        """Clock mode: one poll (after connecting, if the link is down and a retry is due),
        then publish what it read."""
        if self._loop is None:
            return
        now = self._now()
        connecting = not self._loop.tracking
        self._loop.step(now)
        if connecting and self._loop.tracking:
            self._loop.step(now)
        self._on_new_pose()

    def _on_new_pose(self) -> None:
        if (self._loop is None or self._pose_pub is None or self._cov_pub is None
                or self._rms_pub is None):
            self._queue.clear()
            return
        now_ros = self.get_clock().now()
        now_link = self._now()
        while self._queue:
            pose, host_time = self._queue.popleft()
            age_ns = int(max(0.0, now_link - host_time) * 1e9)
            # clamped: under use_sim_time the clock can be younger than the frame's wall age
            # (clock mode polls and publishes at one instant: age 0, the clock's own stamp)
            stamp = now_ros.to_msg() if age_ns == 0 else rclpy.time.Time(
                nanoseconds=max(0, now_ros.nanoseconds - age_ns),
                clock_type=now_ros.clock_type).to_msg()
            frame_id = self.config.frame_id
            self._pose_pub.publish(tip_pose_to_msg(pose, stamp, frame_id, out=self._pose_msg))
            self._cov_pub.publish(tip_pose_to_cov_msg(pose, stamp, frame_id, out=self._cov_msg))
            self._rms_pub.publish(Float64(data=pose.rms_error_m))
            if self._tf_pub is not None:
                self._tf_pub.publish(tip_tf(pose, stamp, frame_id, self.config.tip_frame_id,
                                            out=self._tf_msg))
            with self._health_lock:
                self.health.published += 1

    def _on_diagnostics_timer(self) -> None:
        if self._loop is None or self._diag_pub is None:
            return  # inactive: nothing is published
        with self._health_lock:
            level, message = self.health.level(self._now(), self.config.stale_after_s)
            values = self.health.values()
        values['port'] = self.config.port
        values['protocol'] = 'BX' if self.config.use_bx else 'TX'
        msg = DiagnosticArray()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.status = [diagnostic_status('aurora: EM tracker', f'ndi_aurora:{self.config.port}',
                                        level, message, values)]
        self._diag_pub.publish(msg)

    def destroy_node(self) -> None:
        """Stop the reader thread (TSTOP, port closed), release the device, destroy the node.

        Safe in every lifecycle state.
        """
        self._stop_reader()
        self._release()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Build the node, configure and activate it (unless ``autostart`` is false), spin.

    ``scripts/ros2run em_tracker aurora_node --ros-args -p port:=...`` (or
    ``scripts/ws aurora_node --ros-args -p port:=...``)
    """
    run_node(AuroraNode, 'aurora_node', args, start=start_lifecycle)


if __name__ == '__main__':
    main()
