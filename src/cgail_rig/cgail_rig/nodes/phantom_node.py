"""Phantom node (``phantom``): the simulated world that closes the rig's loop.

Run: ``ros2 run cgail_rig phantom_node`` (pip-only workspace: ``scripts/ros2run
cgail_planner phantom_node``); normally started by ``cgail session`` or ``cgail launch
launch/sim_rig.launch.yaml --in-process``. Its topics are its own, under its name
(``~/tip_pose``, ``~/target``, ``~/aurora_port``, ``~/markers``, ``~/pressures``,
``~/insertion_state``); below they are named as in the rig, whose launch files remap them
(docs/interfaces.md).

It hosts the simulated devices in this process and the catheter-in-aorta physics
(:mod:`cgail_rig.core.phantom`):

* a simulated NDI Aurora on a pty (``em_tracker.hw.sim_aurora``) whose pose source is the true
  tip pose plus EM noise; the port (a symlink, ``aurora_link``) is published on
  ``phantom/aurora_port`` for ``aurora_node``'s ``port`` parameter;
* the simulated PAM regulator bank and the simulated sleeve driver on python-can VIRTUAL buses
  (``pam_channel``, ``driver_channel``): a virtual bus only connects objects of one process, so
  ``pam_node`` and ``driver_node`` must run in this process with ``simulate_regulators`` /
  ``simulate_device`` false (the launcher's ``--in-process`` mode);
* the true catheter plant (:mod:`cgail_rig.core.plant`, parameter ``plant``): it reads only
  what a real catheter feels, the pressures the bank holds and the catheter's motion at the
  driver's gripper, and turns them into the real bend (dead zone, McKibben pair, Bouc-Wen
  hysteresis, cross-coupling, lag) and the tip's real advance (slip under load, backlash).
  ``'true'`` draws it from its sourced ranges with ``plant_seed``; ``'ideal'`` is the old world
  (the PAM controller's nominal model on the true pressures, the tip advances as the gripper).
  The phantom never reads a controller's estimate (no ``catheter/bend_state``); without a
  hosted bank it reads the measured ``pam/pressures``, without a hosted driver the driver's
  ``catheter/insertion_state``;
* the physics: the tip advances by the plant's advance and curves with its bend (per inserted
  dl the heading turns by bend * dl / L), the wall (static, or deformable + heartbeat)
  constrains it and the compliant tip turns away from it. With ``fixture: bench`` the catheter
  is clamped at the base of its steerable segment (the start pose) in free air instead, and
  the tip is the arc of the plant's current bend (``cgail identify-pam`` identifies the actuators
  so, as a rig team does on the bench);
* ``phantom/lumen`` (visualization_msgs/MarkerArray, latched, frame ``phantom``): the lumen
  (TRIANGLE_LIST ``lumen`` on the wall's current vertices, decimated above
  ``marker_max_triangles``). A static wall is published once, at start: the latched sample
  reaches every late joiner (a viewer, a recorder). A dynamic wall is published again only
  when it moved, at most every ``1 / lumen_rate_hz`` s (above twice the 70-bpm heartbeat by
  default, so a viewer's wall does not alias).
* ``phantom/markers`` (visualization_msgs/MarkerArray, latched, frame ``phantom``): the
  catheter body (LINE_STRIP ``catheter_body``), a full snapshot every ``1 / marker_rate_hz`` s
  (:mod:`cgail_planner.core.markers`).

  Both are built only while someone subscribes (the first one always goes out, for late
  joiners of the latched topic).

Time, two ways:

* ``lockstep: true`` (``cgail session``): the lockstep executor
  (:mod:`cgail_rig.lockstep`) owns the simulated clock of every node of the rig and
  calls :meth:`PhantomNode.advance` at the start of each tick; stamps are the node clock
  (simulated time from 0). Results are then a function of seed and configuration only.
* otherwise (``cgail launch ... --in-process``): one steady-clock timer steps devices and physics
  by ``1 / physics_rate_hz`` simulated seconds every ``1 / (physics_rate_hz * time_scale)`` wall
  seconds. With ``publish_clock`` the simulated time goes out on ``/clock`` and the other nodes
  run with ``use_sim_time``, so the rig runs ``time_scale`` times faster than real time (it slows
  down, never takes bigger steps, when the CPU cannot keep up).
"""

from __future__ import annotations

from dataclasses import replace
import os
from pathlib import Path
import tempfile
import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PointStamped, PoseStamped
import numpy as np
from rclpy.clock import Clock, ClockType, ROSClock
from rclpy.node import Node
from rclpy.time import Time
from rosgraph_msgs.msg import Clock as ClockMsg
from sensor_msgs.msg import JointState
from std_msgs.msg import Float64MultiArray, Header, String
from std_srvs.srv import Trigger
from visualization_msgs.msg import Marker, MarkerArray

from cgail_node_utils.entry_point import run_node
from cgail_planner.core.errors import InvalidInputError
from cgail_planner.core.markers import body_marker, LumenMesh, MarkerConfig
from cgail_planner.core.rotations import matrix_to_quaternion
from cgail_planner.nodes import conversions as conv
from cgail_rig.core.faults import (
    CapMonitor,
    Caps,
    Fault,
    FAULT_KINDS,
    plan_fault,
    push_direction,
    push_offset,
    SleeveSlip,
)
from cgail_rig.core.phantom import FIXTURES, PhantomConfig, PhantomPhysics
from cgail_rig.core.plant import make_plant
from cgail_sim.ftl_model import CatheterConfig
from cgail_sim.mesh_io import AnatomyError
from cgail_sim.wall import WallError


class PhantomNode(Node):
    """Simulated phantom + devices (module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('phantom', **kwargs)
        d = PhantomConfig()
        self.config = PhantomConfig(
            catheter=CatheterConfig(segment_length=conv.declare(
                self, 'segment_length', d.catheter.segment_length,
                'steerable segment length L, m', lo=1e-3, hi=0.5)),
            em_noise_rms=conv.declare(self, 'em_noise_m', d.em_noise_rms,
                                      'RMS of the EM position noise, m', lo=0.0, hi=0.01),
            em_angle_noise_rms=conv.declare(self, 'em_angle_noise_rad', d.em_angle_noise_rms,
                                            'RMS of the EM orientation noise, rad',
                                            lo=0.0, hi=0.1),
            wall_dt=conv.declare(self, 'wall_dt_s', d.wall_dt, 'dynamic mode: step of the '
                                 'deformable wall (PBD + heartbeat), s', lo=1e-3, hi=0.2))
        fixture = conv.declare(self, 'fixture', d.fixture, "'none' (the catheter in the "
                               "aorta) or 'bench' (clamped at the base of the steerable segment, "
                               'in free air: the tip is the arc of the bend, the insertion is '
                               'ignored; cgail identify-pam)')
        if fixture not in FIXTURES:
            raise ValueError(f'fixture must be one of {FIXTURES}, found {fixture!r}')
        self.config = replace(self.config, fixture=fixture)
        anatomy = conv.declare(self, 'anatomy', 'default', "the phantom's anatomy: a built-in "
                               "name ('default', 'elongated'), a prepared anatomy directory or a "
                               'mesh file with its <stem>.yaml landmarks')
        self.mode = conv.declare(self, 'mode', 'static', "'static' (rigid wall) or 'dynamic' "
                                 '(deformable wall, heartbeat, moving target)')
        if self.mode not in ('static', 'dynamic'):
            raise ValueError(f"mode must be 'static' or 'dynamic', found {self.mode!r}")
        self.start_id = conv.declare(self, 'start_id', 0, 'start configuration', lo=0, hi=99)
        self.target_id = conv.declare(self, 'target_id', 0, 'target', lo=0, hi=99)
        self.physics_dt = 1.0 / conv.declare(self, 'physics_rate_hz', 50.0,
                                             'physics and device step rate, Hz (sim time)',
                                             lo=1.0, hi=1000.0)
        self.time_scale = conv.declare(self, 'time_scale', 1.0, 'simulated seconds per wall '
                                       'second', lo=0.01, hi=100.0)
        self.publish_clock = conv.declare(self, 'publish_clock', False,
                                          'publish the simulated time on /clock')
        self.lockstep = conv.declare(self, 'lockstep', False, 'stepped by the lockstep '
                                     'executor (advance() each tick, node-clock stamps) instead '
                                     'of its own steady-clock timer')
        link = conv.declare(self, 'aurora_link', '', 'symlink to the simulated Aurora pty '
                            "('' = <tmp>/cgail_sim_aurora_<pid>)")
        sim_aurora = conv.declare(self, 'simulate_aurora', True, 'host the simulated Aurora')
        sim_bank = conv.declare(self, 'simulate_regulators', True,
                                'host the simulated PAM regulator bank (virtual CAN)')
        pam_channel = conv.declare(self, 'pam_channel', 'pam0', 'virtual CAN channel of the bank')
        sim_driver = conv.declare(self, 'simulate_driver', True,
                                  'host the simulated sleeve driver (virtual CAN)')
        driver_channel = conv.declare(self, 'driver_channel', 'sleeve_driver',
                                      'virtual CAN channel of the sleeve driver')
        self.frame_id = conv.declare(self, 'frame_id', 'phantom', 'frame of published poses')
        pose_rate = conv.declare(self, 'pose_rate_hz', 10.0, 'rate of phantom/tip_pose (the '
                                 'true pose), Hz (sim time)', lo=0.1, hi=1000.0)
        self._pose_every = max(1, round(1.0 / (pose_rate * self.physics_dt)))
        m = MarkerConfig()
        self.marker_config = MarkerConfig(max_triangles=conv.declare(
            self, 'marker_max_triangles', m.max_triangles, 'phantom/lumen: the lumen is '
            'decimated above this many triangles', lo=100, hi=100_000))
        marker_rate = conv.declare(self, 'marker_rate_hz', 5.0, 'rate of phantom/markers '
                                   '(the catheter body), Hz', lo=0.1, hi=30.0)
        lumen_rate = conv.declare(self, 'lumen_rate_hz', 5.0, 'dynamic mode: highest rate of '
                                  'phantom/lumen, republished only when the wall moved (a '
                                  'static wall goes out once), Hz', lo=0.1, hi=30.0)
        seed = conv.declare(self, 'seed', 0, 'seed of the EM noise', lo=0, hi=2**31 - 1)
        self.plant_kind = conv.declare(self, 'plant', 'true', "the catheter plant: 'true' "
                                       "(drawn from its sourced ranges with plant_seed), "
                                       "'nominal' (its nominal values) or 'ideal' (the PAM "
                                       "controller's nominal model, the old world)")
        if self.plant_kind not in ('true', 'nominal', 'ideal'):
            raise ValueError(f"plant must be 'true', 'nominal' or 'ideal', found "
                             f"{self.plant_kind!r}")
        plant_seed = conv.declare(self, 'plant_seed', -1, "seed of the true plant's draw "
                                  "(-1: the 'seed' parameter)", lo=-1, hi=2**31 - 1)
        self.plant_seed = seed if plant_seed < 0 else plant_seed
        diag_period = conv.declare(self, 'diagnostics_period_s', 1.0, '/diagnostics period, s',
                                   lo=0.05, hi=60.0)
        fault_kind = conv.declare(self, 'fault', '', "fault to inject ('' none, or one of "
                                  f'{FAULT_KINDS}; cgail_rig.core.faults)')
        if fault_kind not in ('', *FAULT_KINDS):
            raise ValueError(f"fault: expected '' or one of {FAULT_KINDS}, found {fault_kind!r}")
        fault_goal_s = conv.declare(self, 'fault_goal_s', 1.0, "simulated time of the trial's "
                                    'goal, s: the fault onset is drawn after it', lo=0.0,
                                    hi=3600.0)

        from cgail_sim.anatomy_spec import anatomy_label
        from cgail_sim.wall import DeformableWall, StaticWall
        from cgail_sim.worlds import load_world

        try:
            self.world = load_world(anatomy)
        except AnatomyError:
            super().destroy_node()  # (no devices started yet)
            raise
        self.anatomy_label = anatomy_label(anatomy)
        sc = self.world.scenarios
        for name, value, n in (('start_id', self.start_id, len(sc.starts)),
                               ('target_id', self.target_id, len(sc.targets))):
            if value >= n:
                raise ValueError(f'{name} must be in [0, {n - 1}], found {value}')
        wall = StaticWall(self.world.anatomy) if self.mode == 'static' \
            else DeformableWall(self.world.anatomy)
        self.wall: StaticWall = wall  # (a DeformableWall in dynamic mode)
        self.plant = make_plant(self.plant_kind, self.plant_seed,
                                segment_length=self.config.catheter.segment_length)
        self.physics = PhantomPhysics(self.config, wall, self.plant)
        self.lumen = LumenMesh(self.world.anatomy, self.marker_config.max_triangles)
        self._lumen_sent: np.ndarray | None = None  # (the wall vertices last published)
        self._markers_sent = False
        # refilled per publish (a publish serializes before it returns: conv.pose_msg's and
        # conv.marker_msg's out): the tip pose, the body snapshot's DELETEALL and LINE_STRIP
        self._pose_msg = PoseStamped()
        self._body_delete = Marker(action=Marker.DELETEALL)
        self._body_msg: Marker | None = None
        #: Why the physics stopped (a deformable wall beyond its bound), '' while it runs.
        self.physics_error = ''
        self.rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self.insertion: float | None = None
        self.pressures = np.zeros(4)
        self.bend = (0.0, 0.0)
        self.sim_time = 0.0
        # free-running: simulated time starts at the wall-clock time of construction (stamps
        # look like the rig's; nodes that subtract a wall-clock age from a stamp never go below
        # zero). Lockstep: the node clock is the simulated time, from 0.
        self._clock_offset = 0.0 if self.lockstep else time.time()
        self._em_cache: tuple[float, np.ndarray, np.ndarray] | None = None
        #: The injected fault (None: none), whether its onset passed, the push direction.
        self.fault: Fault | None = plan_fault(fault_kind, seed, fault_goal_s) \
            if fault_kind else None
        self.fault_started = False
        #: ``stuck_pam``: simulated time the stuck chamber became observable (the bank's
        #: ``stuck_observable_at`` on this clock), None while it is not (cgail_rig.core.faults).
        self.fault_observable_at: float | None = None
        self._slip = SleeveSlip()
        self._push_dir: np.ndarray | None = None
        #: The catheter's largest tip speed, bend and pressure, measured on the plant.
        self.caps = CapMonitor(Caps())
        self.reset_trial(self.start_id, self.target_id)

        self.devices: list[object] = []
        self.bank = self.driver = self.aurora = None
        if sim_bank:
            from pam_controller.hw.sim_regulators import SimRegulatorBank, SimRegulatorConfig
            self.bank = SimRegulatorBank(SimRegulatorConfig(channel=pam_channel))
        if sim_driver:
            from catheter_driver.hw.sim_driver import SimulatedDriver
            self.driver = SimulatedDriver(driver_channel)
        self.aurora_port = ''
        if sim_aurora:
            from em_tracker.hw.sim_aurora import SimAurora
            link = link or str(Path(tempfile.gettempdir()) / f'cgail_sim_aurora_{os.getpid()}')
            self.aurora = SimAurora(self._em_pose, link_path=link,
                                    clock=lambda: self.sim_time).start()
            self.aurora_port = self.aurora.port

        self._pose_pub = self.create_publisher(PoseStamped, '~/tip_pose', conv.SENSOR_QOS)
        self._target_pub = self.create_publisher(PointStamped, '~/target', conv.LATCHED_QOS)
        self._port_pub = self.create_publisher(String, '~/aurora_port', conv.LATCHED_QOS)
        self._diag_pub = self.create_publisher(DiagnosticArray, '/diagnostics',
                                               conv.DIAGNOSTICS_QOS)
        self._markers_pub = self.create_publisher(MarkerArray, '~/markers', conv.LATCHED_QOS)
        self._lumen_pub = self.create_publisher(MarkerArray, '~/lumen', conv.LATCHED_QOS)
        self._clock_pub = self.create_publisher(ClockMsg, '/clock', 10) \
            if self.publish_clock else None
        if self.driver is None:  # (a hosted driver's gripper is read directly)
            self.create_subscription(JointState, '~/insertion_state', self._on_insertion,
                                     conv.SENSOR_QOS)
        if self.bank is None:  # (a hosted bank's pressures are read directly)
            self.create_subscription(Float64MultiArray, '~/pressures', self._on_pressures,
                                     conv.SENSOR_QOS)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self._port_pub.publish(String(data=self.aurora_port))
        self._ticks = 0
        self.publish_target()
        self.publish_lumen()
        self.publish_markers()
        dynamic = self.mode == 'dynamic'  # (a static wall's lumen went out above, once)
        if self.lockstep:
            self.create_timer(diag_period, self._on_diagnostics)
            self.create_timer(1.0 / marker_rate, self.publish_markers)
            if dynamic:
                self.create_timer(1.0 / lumen_rate, self.publish_lumen)
        else:
            steady = Clock(clock_type=ClockType.STEADY_TIME)
            self.create_timer(self.physics_dt / self.time_scale, self._on_tick, clock=steady)
            self.create_timer(diag_period, self._on_diagnostics, clock=steady)
            self.create_timer(1.0 / marker_rate, self.publish_markers, clock=steady)
            if dynamic:
                self.create_timer(1.0 / lumen_rate, self.publish_lumen, clock=steady)
        timing = 'lockstep' if self.lockstep else (
            f'x{self.time_scale:g} time{" on /clock" if self.publish_clock else ""}')
        self.get_logger().info(
            f'phantom: {self.anatomy_label} ({self.mode}), start {self.start_id}, target '
            f'{self.target_id}, aurora port {self.aurora_port or "-"}, {timing}')

    # ------------------------------------------------------------------ trial control
    def reset_trial(self, start_id: int, target_id: int) -> None:
        """Put the catheter back at start ``start_id`` with target ``target_id``."""
        sc = self.world.scenarios
        if not (0 <= start_id < len(sc.starts) and 0 <= target_id < len(sc.targets)):
            raise ValueError(f'start_id must be in [0, {len(sc.starts) - 1}] and target_id in '
                             f'[0, {len(sc.targets) - 1}], found {start_id}, {target_id}')
        start = sc.starts[start_id]
        with self._lock:
            self.start_id, self.target_id = start_id, target_id
            self.physics.reset(start.position, start.rotation, start.introducer)

            self._em_cache = None
        if hasattr(self, '_target_pub'):
            self.publish_target()

    def target_position(self) -> np.ndarray:
        """(3,) current target position (moves with its wall particle in dynamic mode), m."""
        t = self.world.scenarios.targets[self.target_id]
        return self.wall.vertex_position(int(t.vertex)) + np.asarray(t.offset)

    def now_msg(self):
        """Stamp of the simulated time (the node clock in lockstep)."""
        if self.lockstep:
            clock = self.get_clock()
            # the constructor's latched messages go out before the lockstep executor adopts
            # the node, while its clock is still the wall clock: they are simulated time 0
            if isinstance(clock, ROSClock) and not clock.ros_time_is_active:
                return Time().to_msg()
            return clock.now().to_msg()
        return Time(nanoseconds=int((self.sim_time + self._clock_offset) * 1e9)).to_msg()

    # ------------------------------------------------------------------ callbacks
    def _on_insertion(self, msg: JointState) -> None:
        try:
            self.insertion = conv.joint_positions(msg, ['insertion'])[0]
        except InvalidInputError as exc:
            self.get_logger().warning(f'insertion state ignored: {exc}',
                                      throttle_duration_sec=2.0)

    def _on_pressures(self, msg: Float64MultiArray) -> None:
        try:
            self.pressures = conv.chamber_pressures(msg)
        except InvalidInputError as exc:
            self.get_logger().warning(f'pressures ignored: {exc}', throttle_duration_sec=2.0)

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response):
        self.reset_trial(self.start_id, self.target_id)
        response.success = True
        response.message = f'reset to start {self.start_id}, target {self.target_id}'
        return response

    def _on_tick(self) -> None:
        self.advance(self.physics_dt)

    def advance(self, dt: float) -> None:
        """Step the simulated devices and the physics by ``dt`` simulated seconds, then publish
        the clock (``publish_clock``), the true pose and, in dynamic mode, the target.

        In lockstep the executor has already moved the node clock to the end of the step.
        """
        if self.fault is not None:
            self._apply_fault(self.sim_time + dt)
        if self.bank is not None:
            self.bank.step(dt)
        if self.driver is not None:
            self.driver.step(dt)
        with self._lock:
            if self.bank is not None:
                self.pressures = self.bank.pressures_pa.copy()
            if self.driver is not None:
                self.insertion = self.driver.mechanism.catheter_position
                if self.fault is not None:  # (the grip transmits the gripper's motion)
                    self.insertion = self._slip.transmit(
                        self.insertion, self.fault.kind == 'slipping_sleeve'
                        and self.fault.active(self.sim_time + dt))
            self.bend = self.plant.bend(self.pressures, dt)
            if not self.physics_error:
                try:
                    self.physics.step(dt, self.insertion, self.bend)
                except WallError as exc:  # safe state: the catheter and the wall freeze
                    self.physics_error = f'physics stopped: {exc}'
                    self.get_logger().error(self.physics_error)
            self.caps.observe(dt, self.physics.last_advance, self.bend, self.pressures)
            if self.lockstep:
                self.sim_time = self.get_clock().now().nanoseconds * 1e-9
            else:
                self.sim_time += dt
        if self.fault_started and self.fault_observable_at is None and self.bank is not None \
                and self.fault is not None and self.fault.kind == 'stuck_pam':
            seen = self.bank.stuck_observable_at(self.fault.channel)
            if seen is not None:  # (the bank's clock is its steps: now is its time_s)
                self.fault_observable_at = self.sim_time - (self.bank.time_s - seen)
                first = self.bank.stuck_error_at(self.fault.channel)
                first_s = self.sim_time - (self.bank.time_s - (seen if first is None else first))
                self.get_logger().warning(
                    f'stuck chamber {self.fault.channel} observable from '
                    f'{self.fault_observable_at:.3f} s (off its setpoint by more than '
                    f'{self.bank.config.stuck_detect_pa / 1e3:g} kPa for '
                    f'{self.bank.config.stuck_detect_s:g} s; first off it at {first_s:.3f} s)')
        stamp = self.now_msg()
        if self._clock_pub is not None:
            self._clock_pub.publish(ClockMsg(clock=stamp))
        self._ticks += 1
        if self._ticks % self._pose_every == 0:
            self._pose_pub.publish(conv.pose_msg(stamp, self.frame_id,
                                                 self.physics.tip_position,
                                                 self.physics.tip_rotation,
                                                 out=self._pose_msg))
        if self.mode == 'dynamic' and self._ticks % 5 == 0:
            self.publish_target()

    def _apply_fault(self, t: float) -> None:
        """Start or end the injected fault at simulated time ``t`` through the simulated
        devices (the Aurora, the regulator bank); the sleeve slip and the push act in
        :meth:`advance` and :meth:`_em_pose`, which also records when a stuck chamber became
        observable (:attr:`fault_observable_at`)."""
        fault = self.fault
        assert fault is not None
        active = fault.active(t)
        if active and not self.fault_started:
            self.fault_started = True
            self.get_logger().warning(f'fault injected: {fault.kind} at {t:.3f} s')
            if fault.kind == 'dropout' and self.aurora is not None:
                self.aurora.inject(missing=True)
            elif fault.kind == 'stuck_pam' and self.bank is not None:
                self.bank.set_stuck(fault.channel)
            elif fault.kind == 'wall_push':
                with self._lock:
                    self._push_dir = push_direction(self.physics.tip_rotation, fault.angle)
        elif self.fault_started and not active and fault.kind == 'dropout' \
                and self.aurora is not None and self.aurora.faults.missing:
            self.aurora.inject(missing=False)

    def publish_target(self) -> None:
        """Publish the current target on ``phantom/target`` (latched)."""
        self._target_pub.publish(conv.point_msg(self.now_msg(), self.frame_id,
                                                self.target_position()))

    def publish_lumen(self) -> None:
        """Publish the lumen on ``phantom/lumen`` (latched) if the wall moved since the last
        one (module docstring)."""
        if self._lumen_sent is not None and self._lumen_pub.get_subscription_count() == 0:
            return
        with self._lock:
            vertices = np.array(self.wall.vertices, dtype=np.float64)
        if self._lumen_sent is not None and np.array_equal(vertices, self._lumen_sent):
            return
        self._lumen_sent = vertices
        self._lumen_pub.publish(conv.marker_array_msg(self.now_msg(), self.frame_id,
                                                      [self.lumen.marker(vertices)]))

    def publish_markers(self) -> None:
        """Publish the catheter body on ``phantom/markers`` (module docstring)."""
        if self._markers_sent and self._markers_pub.get_subscription_count() == 0:
            return
        with self._lock:
            body = body_marker(self.physics.catheter, 0, self.marker_config.body_spacing)
        # (conv.marker_array_msg's snapshot, its two markers refilled)
        header = Header(stamp=self.now_msg(), frame_id=self.frame_id)
        self._body_delete.header = header
        markers = [self._body_delete]
        if body is not None:
            self._body_msg = conv.marker_msg(header, body, out=self._body_msg)
            markers.append(self._body_msg)
        self._markers_pub.publish(MarkerArray(markers=markers))
        self._markers_sent = True

    def _em_pose(self, t_frame: float) -> tuple[np.ndarray, np.ndarray]:
        """Pose source of the simulated Aurora: mm and (w, x, y, z), one noise draw per frame."""
        with self._lock:
            cache = self._em_cache
            if cache is None or cache[0] != t_frame:
                p, r = self.physics.measured_pose(self.rng)
                if self._push_dir is not None and self.fault is not None:
                    p = p + push_offset(self.fault, self.sim_time, self._push_dir)
                x, y, z, w = matrix_to_quaternion(r)
                cache = (t_frame, p * 1e3, np.array([w, x, y, z]))
                self._em_cache = cache
        return cache[1].copy(), cache[2].copy()

    def diagnostics(self) -> DiagnosticArray:
        """Current diagnostics of the simulated phantom."""
        p = self.physics.tip_position
        dist = float(np.linalg.norm(self.target_position() - p))
        values = [('sim_time_s', f'{self.sim_time:.2f}'), ('mode', self.mode),
                  ('start_id', self.start_id), ('target_id', self.target_id),
                  ('tip_m', np.round(p, 5).tolist()), ('target_distance_mm', f'{dist * 1e3:.1f}'),
                  ('inserted_mm', f'{self.physics.inserted * 1e3:.1f}'),
                  ('wall_contacts', self.physics.contacts),
                  ('insertion_jumps', self.physics.insertion_jumps),
                  ('aurora_port', self.aurora_port),
                  ('plant', self.plant_kind), ('plant_seed', self.plant_seed),
                  ('pressures_kpa', np.round(self.pressures / 1e3, 1).tolist()),
                  ('bend_rad', [round(b, 4) for b in self.bend]),
                  ('insertion_m', self.insertion),
                  ('tip_advance_m', round(self.plant.tip, 6))]
        level = DiagnosticStatus.OK if self.insertion is not None else DiagnosticStatus.WARN
        message = 'simulating' if self.insertion is not None else 'no insertion state yet'
        if self.config.fixture == 'bench':
            level, message = DiagnosticStatus.OK, 'bench fixture: clamped at the segment base'
        if self.physics_error:
            level, message = DiagnosticStatus.ERROR, self.physics_error
        return conv.diagnostics(self.now_msg(), 'phantom: simulated rig', 'phantom', level,
                                message, values)

    def _on_diagnostics(self) -> None:
        self._diag_pub.publish(self.diagnostics())

    def destroy_node(self) -> None:
        """Stop the simulated devices, then the node."""
        if self.aurora is not None:
            self.aurora.close()
        for dev in (self.bank, self.driver):
            if dev is not None:
                dev.stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> None:
    """Console script ``phantom_node``."""
    run_node(PhantomNode, 'phantom_node', args, fatal=(AnatomyError,))


if __name__ == '__main__':
    main()
