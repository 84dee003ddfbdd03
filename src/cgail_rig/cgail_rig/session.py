"""``cgail session``: the simulated in-vitro session of the paper (section IV-B), end to end.

    cgail session --out runs/invitro                                   # the main job
    cgail session --trials 2 --policy model.onnx --mode dynamic --out runs/invitro_dynamic

**Protocol.** ``--trials`` trials (default 30, against the paper's 10: at 10 per condition no
difference was significant in our sessions) following the C-GAIL path, then as many following
the centerline (``planner_type: centerline``); trial ``k`` of a condition starts at start
``k mod 3`` with target ``k mod 5``. Each trial runs on a rig of its own, built from
``launch/sim_rig.launch.yaml``: ``phantom`` (the catheter-in-aorta physics, a simulated Aurora
on a pty, the regulator bank and the sleeve driver on virtual CAN), the real ``aurora`` node
(``link: in_process``: the simulated Aurora answers its Combined API commands in the polling
thread, no pty round trip per frame; ndicapi over the pty is the rig's path),
``pam_controller``, ``sleeve_driver``, ``teleop``, ``planner`` and the scripted ``operator`` at
the gamepad. After 1 s of simulated time (the tracker connects, the
first poses arrive) the goal is published; the trial ends when the operator stops (target
reached, or closest approach passed) or at the 3-minute limit, and is recorded to its own bag.
If the beating wall blows up (the phantom freezes its physics, :class:`~cgail_sim.wall.
WallError`), the trial ends at once as ``simulation fault`` with the anatomy, the seed and the
time; its bag is evaluated as a failure, the session goes on, and the report counts the faults.
Then the offline metrics (``cgail bag metrics``) print the markdown table with the paper's in-vitro
numbers side by side and write the box plots.

**Autonomy conditions** (docs/guides/autonomy.md). ``autonomous``, ``autonomous-policy`` and
``shared`` replace ``teleop`` with ``autonomy_node`` (path tracker, the ONNX policy of
``--policy``, or the path tracker corrected by the scripted operator in its supervising role,
who holds the deadman) along the planner's C-GAIL path, under the safety supervisor; the trial
ends when ``autonomy/state`` reads ``done`` or ``stopped:<reason>``, or at the limit.
``--faults`` injects a fault into each of their trials (:mod:`cgail_rig.core.faults`); the
report adds the end states, each fault's detection time against its bound (a miss flagged; a
stuck PAM's counted from when it became observable, one never observable counted apart) and
the caps measured on the true plant. The guided trials are the same with or without them.

**Operator practice** (:mod:`cgail_planner.core.operator`). The paper's participant did 10
pre-training trials per condition before its 10 measured ones. The scripted operator's skill
follows a learning curve of the number of trials it did before (the power law of practice), so
``--pretrain N`` (default 10) starts trial ``k`` of each condition at the skill after ``N + k``
trials of that condition (each condition pre-trained on its own, as in the paper, and never
favoured by the order the conditions run in). The pre-training trials are modelled, not run:
the skill depends on their number only, not on their outcome, so running them could not change
a measured trial (a trial is a function of the session seed and its index). To watch the
learning curve itself, record the pre-training too: ``--pretrain 0 --trials 20``.

**The plant** (:mod:`cgail_rig.core.plant`, ``docs/plant.md``). The phantom moves the
catheter by its own true plant, drawn once per session with ``--seed``, from the regulators'
measured pressures and the gripper's position. ``--plant identified`` (the default) first runs
``cgail identify-pam``'s simulated bench on that plant (cached in ``<out>/identification/``) and
gives the PAM controller the identified model, as a rig team does before a session; ``nominal``
keeps the controller's nominal model on the same plant; ``ideal`` makes the plant the
controller's own nominal model with a kinematic tip and no sleeve slip (the old rig, for
comparison; not an upper bound: without the compliant tip, its tip strays farther from the path
in the arch).

**Simulated time is the only time** (:mod:`cgail_rig.lockstep`). The rig's nodes run
on one lockstep executor that owns their clocks: a tick advances the simulated clock by
``1 / --physics-rate`` s, steps the phantom, fires the due timers and returns only when every
message of the tick has been handled. The simulated devices are stepped by the phantom, the
Aurora node polls from a timer of its clock (``poll_mode: clock``), and every watchdog reads
the node clock. A trial is therefore a function of the configuration and of its seed
(``--seed`` with the condition and trial index), never of the host: the same command gives the
same bags and metrics at any load, in any order and in any worker. It runs as fast as the CPU
allows (``--time-scale`` caps it, e.g. 1 to watch it live with ``--gui``).

**Parallel trials.** ``--jobs N`` (default: the number of CPUs) runs the trials in N worker
processes, each with its own rig, ROS domain and time source; the results equal ``--jobs 1``.
The workers start before the PAM model is identified and warm up meanwhile (imports, domain
probe, one throw-away rig: :class:`Workers`), as many at once as there are cores besides the
identification's; each trial's bag is evaluated as the trial ends, while the others run. Neither
changes a bag or a number: what a trial records does not depend on what ran before it.

**Isolation** (:mod:`cgail_rig.domain`). Every rig runs on a ROS domain of its own:
a free one picked automatically and printed, or ``ROS_DOMAIN_ID`` if set (then the trials run
one at a time on it). A session refuses to start on a domain where device nodes (``aurora``,
``pam_controller``, ``sleeve_driver``) answer that it did not start: a simulated session must
never command a real rig.

**Console.** One line per trial (with the elapsed time and an estimate of the time left, at
the pace of the trials done so far), then the table, then where the time went (``phases:``
start, identification, trials, report); the nodes' logs go to ``<out>/logs/`` (the
identification's bench and the workers' warm-up rigs too).

**Bags.** Each trial's bag is zstd-compressed MCAP; the lumen is on its own latched topic
(``phantom/lumen``: a static wall recorded once, a dynamic one when it moved, at most at
``RECORDED_LUMEN_RATE_HZ``), the catheter body on ``phantom/markers``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Mapping, Sequence
import concurrent.futures
import contextlib
import dataclasses
from dataclasses import dataclass, field
import functools
import gc
import math
import multiprocessing
import os
from pathlib import Path
import shutil
import signal
import sys
import tempfile
import time
from typing import Any

from cgail_rig.core.faults import FAULT_KINDS
from cgail_rig.launch_spec import default_launch_file
from cgail_sim.cli_help import tool_parser

#: Recorded in every trial's bag: what the metrics read, and what RViz2 / Foxglove show (TF, the
#: tip with its covariance, the markers: the lumen, the catheter body, the plan).
TOPICS = ('em_tracker/tip_pose', 'planner/path', 'planner/goal', 'planner/next_waypoint',
          'planner/suggested_bend', 'phantom/tip_pose', 'em_tracker/tip_pose_cov', '/tf',
          '/tf_static', 'phantom/lumen', 'phantom/markers', 'planner/markers')
#: The guided conditions (the paper's): the scripted operator drives ``teleop`` from the
#: planner's guidance, along the C-GAIL path or the centerline. The default.
CONDITIONS = ('cgail', 'centerline')
#: The autonomy's conditions (issue 36): ``autonomy_node`` drives the catheter along the
#: planner's C-GAIL path, under its supervisor: ``autonomous`` (the path tracker, the default
#: controller), ``autonomous-policy`` (the ONNX policy controller), ``shared`` (the path
#: tracker, the scripted operator supervising: deadman held, corrections beyond a threshold).
AUTONOMY_CONDITIONS = ('autonomous', 'autonomous-policy', 'shared')
ALL_CONDITIONS = CONDITIONS + AUTONOMY_CONDITIONS
#: The autonomy's bend cap in a session, rad: below the catheter's pi/2 by the identified
#: PAM model's error on the true plant (a commanded pi/2 bent it to ~1.69 rad, +8 %; the policy
#: controller's fast reversals of a commanded 1.4 rad to 1.59 rad, +14 %, hysteresis), so the
#: plant's bend stays under pi/2 (docs/guides/autonomy.md).
AUTONOMY_MAX_BEND = 1.3
#: Recorded besides ``TOPICS`` in a trial of an autonomy condition.
AUTONOMY_TOPICS = ('autonomy/state',)
#: ``--plant``: the true plant with the controller's nominal model, the true plant with the
#: model identified on it, or the controller's own model as the plant.
PLANTS = ('nominal', 'identified', 'ideal')
#: Recorded latched topics with a sample before the trial starts (published while the rig is
#: built, before the recorder subscribes): the recorder must hold them before the first tick.
LATCHED_AT_START = ('/tf_static', '/phantom/lumen', '/phantom/markers')
#: The lumen on ``phantom/lumen`` in a trial's bag: decimated to this many triangles. A static
#: wall is recorded once (the latched sample at the start); a dynamic one again whenever it
#: moved, at most at ``RECORDED_LUMEN_RATE_HZ`` (above twice the 70-bpm heartbeat, 1.17 Hz, so
#: the replayed wall does not alias). The catheter body (``phantom/markers``) is recorded at
#: ``RECORDED_MARKER_RATE_HZ``.
RECORDED_LUMEN_TRIANGLES = 600
RECORDED_LUMEN_RATE_HZ = 2.5
RECORDED_MARKER_RATE_HZ = 3.0
#: Simulated seconds between the rig's start and the goal (the tracker connects, poses flow).
SETTLE_S = 1.0
#: Simulated seconds recorded after the operator stopped.
TAIL_S = 0.2
#: Simulated seconds between two sweeps of the rig for what reached it from outside (a
#: message, a service request such as ``ros2 param set``): nothing outside talks to a session's
#: rig, so it need not be polled on every tick (:class:`~cgail_rig.lockstep.LockstepExecutor`,
#: ``sweep_every``).
SWEEP_S = 0.25
#: ros-args of every rig context: node logs go to the log file only.
ROS_ARGS = ['--ros-args', '--disable-stdout-logs', '--disable-rosout-logs']


def default_policy(anatomy: str = 'default', mode: str = 'static') -> Path:
    """The committed C-GAIL policy for the built-in ``anatomy`` in ``mode`` (installed with the
    package): ``cgail_planner/models/cgail_<anatomy>_<mode>.onnx``, or the anatomy's static policy
    when there is no policy re-trained for that mode. The path may not exist (no policy for
    that anatomy; a path anatomy never has one)."""
    import cgail_planner

    models = Path(cgail_planner.__file__).resolve().parent / 'models'
    path = models / f'cgail_{anatomy}_{mode}.onnx'
    return path if path.is_file() else models / f'cgail_{anatomy}_static.onnx'


@dataclass(frozen=True)
class SessionSettings:
    """What every trial of a session shares (picklable: it goes to the worker processes)."""

    anatomy: str = 'default'
    """A built-in anatomy name, or the absolute path of a prepared anatomy directory or mesh
    file (every node of every trial resolves the same one)."""
    mode: str = 'static'
    """'static' (rigid phantom) or 'dynamic' (deformable beating wall, moving target)."""
    policy: str = ''
    """ONNX C-GAIL policy of the cgail condition."""
    time_limit: float = 180.0
    """Trial time limit, simulated s (paper: 180)."""
    physics_rate: float = 40.0
    """Lockstep tick rate = phantom physics and simulated devices, Hz of simulated time (40:
    one tick per Aurora frame, so the tracker delivers every frame; control loops at half)."""
    tracker_rate: float = 40.0
    """EM tracker frame rate, Hz of simulated time (the Aurora: 40)."""
    launch_file: str = ''
    """Rig launch YAML; '' = the package's sim_rig.launch.yaml."""
    time_scale: float = 0.0
    """At most this many simulated seconds per wall second; 0 = as fast as the CPU allows."""
    gui: bool = False
    """Also run the guidance GUI (gui_node) in the rig."""
    gui_port: int = 8780
    """Port of the guidance GUI."""
    igtl: bool = False
    """Also run ``igtl_bridge`` (3D Slicer over OpenIGTLink) in the rig."""
    igtl_port: int = 18944
    """Port of ``igtl_bridge``'s server (loopback)."""
    foxglove: bool = False
    """Also run ``foxglove_bridge`` (the live Foxglove view) in the rig."""
    foxglove_port: int = 8765
    """Port of ``foxglove_bridge``'s WebSocket server (loopback)."""
    plant: str = 'true'
    """The phantom's catheter plant: 'true' (drawn from its sourced ranges with
    ``plant_seed``) or 'ideal' (the PAM controller's nominal model,
    :mod:`cgail_rig.core.plant`)."""
    pam_parameters: tuple[tuple[str, float], ...] = ()
    """pam_controller parameters over the rig's (``--plant identified``: the bending model
    identified on this plant, ``identify_pam``); empty: its nominal model."""
    plant_seed: int = 0
    """Seed of the true plant's draw: the session's ``--seed``, so every trial of a session,
    in both conditions, runs the same catheter (a rig has one), which the controller's nominal
    model misses by the same amount."""
    autonomy_policy: str = ''
    """ONNX policy of the ``autonomous-policy`` condition (default: ``policy``)."""


@dataclass(frozen=True)
class TrialSpec:
    """One trial: its condition, index, start, target, seed and bag."""

    condition: str
    index: int
    """0-based index within the condition."""
    start_id: int
    target_id: int
    seed: int
    """Seed of the EM noise and of the operator's stick noise of this trial."""
    bag: str
    practice: int = 0
    """Trials of this condition the operator did before this one (pre-training included)."""
    skill: float = 1.0
    """The operator's skill level in this trial (``skill_after(practice)``; 1: practised)."""
    fault: str = ''
    """Fault injected in this trial ('' none; :data:`cgail_rig.core.faults.FAULT_KINDS`)."""

    @property
    def label(self) -> str:
        """``<condition>_<nn>``, as the bag is named."""
        return f'{self.condition}_{self.index + 1:02d}'


@dataclass
class TrialResult:
    """What a trial produced (besides its bag)."""

    spec: TrialSpec
    outcome: str = ''
    """The operator's reason to stop, or why the trial could not run."""
    sim_s: float = 0.0
    """Simulated seconds from the goal to the end of the trial."""
    ticks: int = 0
    wall_s: float = 0.0
    domain_id: int = -1
    messages: dict[str, int] = field(default_factory=dict)
    """Recorded messages per topic."""
    callback_errors: list[str] = field(default_factory=list)
    unscheduled: int = 0
    """Messages that reached the rig from outside it during the trial (0 when isolated)."""
    failed: bool = False
    """The trial could not run (rig error), as opposed to a trial outcome."""
    fault: FaultRecord | None = None
    """The injected fault and what the supervisor made of it (None: no fault)."""
    caps_exceeded: list[str] = field(default_factory=list)
    """Caps the catheter exceeded on the true plant (autonomy conditions; empty: none)."""
    caps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Largest tip speed (m/s), bend (rad) and chamber pressure (Pa) on the true plant."""


@dataclass(frozen=True)
class FaultRecord:
    """An injected fault's onset and the supervisor's answer, in simulated seconds."""

    kind: str
    onset_s: float
    """Onset, simulated s from the goal (NaN: the trial ended before it)."""
    stop_reason: str = ''
    """The supervisor's stop reason ('' : it did not stop)."""
    detection_s: float = float('nan')
    """Detection time (:func:`cgail_rig.core.faults.detection_time`), simulated s: onset to
    stop; ``stuck_pam``: observable to stop, 0 for a stop before it was observable (NaN: no
    stop at or after the onset)."""
    bound_s: float = float('nan')
    """The stated detection bound of the kind, s."""
    observable_s: float = float('nan')
    """``stuck_pam``: simulated s from the onset to when the stuck chamber became observable
    (NaN: never before the trial ended, or another kind)."""

    @property
    def injected(self) -> bool:
        """Whether the trial lasted until the onset."""
        return self.onset_s == self.onset_s

    @property
    def caught(self) -> bool:
        """Stopped by the supervisor at or after the onset, within the bound (``stuck_pam``:
        before the chamber became observable, or within the bound after)."""
        return self.detection_s == self.detection_s and self.detection_s <= self.bound_s + 1e-9

    @property
    def never_observable(self) -> bool:
        """A stuck PAM injected, never observable before the trial ended and not stopped after
        the onset: it was never asked for long for a pressure it could not deliver, so nothing
        could tell it from a healthy chamber; neither caught nor missed."""
        return self.kind == 'stuck_pam' and self.injected \
            and self.observable_s != self.observable_s and self.detection_s != self.detection_s

    @property
    def missed(self) -> bool:
        """Injected, observable (every kind but a never observable stuck PAM), not caught."""
        return self.injected and not self.caught and not self.never_observable


def trial_seed(seed: int, condition: str, index: int) -> int:
    """Seed of one trial from the session seed: independent of the order trials run in."""
    import numpy as np

    entropy = [int(seed), ALL_CONDITIONS.index(condition) if condition in ALL_CONDITIONS
               else 99, int(index)]
    return int(np.random.SeedSequence(entropy).generate_state(1)[0] & 0x7FFFFFFF)


def plan_trials(conditions: Sequence[str], trials: int, seed: int, bags_dir: Path,
                n_starts: int = 3, n_targets: int = 5, pretrain: int = 10,
                faults: Sequence[str] = ()) -> list[TrialSpec]:
    """The session's trials in protocol order; trial ``k`` of a condition follows ``pretrain``
    pre-training trials and ``k`` measured ones (``practice``, ``skill``). With ``faults``,
    trial ``k`` of an autonomy condition has fault ``faults[k mod len(faults)]``."""
    from cgail_planner.core.operator import skill_after

    return [TrialSpec(condition, k, k % n_starts, k % n_targets, trial_seed(seed, condition, k),
                      str(bags_dir / condition / f'{condition}_{k + 1:02d}'),
                      practice=pretrain + k, skill=skill_after(pretrain + k),
                      fault=faults[k % len(faults)] if faults and condition in
                      AUTONOMY_CONDITIONS else '')
            for condition in conditions for k in range(trials)]


@functools.lru_cache(maxsize=4)
def rig_launch(path: str, given: tuple[tuple[str, str], ...]) -> Any:
    """The rig's launch file at ``path``, with those of the ``given`` arguments it declares (and
    the overrides of :class:`TrialRig`), each node's parameter files read into its parameters
    (in ``build_node``'s order: the files', then the node's own); read once per process.

    Every trial's rig is built from it: parsing the launch file (twice) and the nodes' parameter
    files again for each trial cost ~30 ms of CPU a trial (YAML), 2 s over the main job's 60.
    """
    from dataclasses import replace

    from cgail_rig.launch_spec import LaunchSpec, load_launch_file, load_params_file

    launch = load_launch_file(Path(path))
    if any(k in launch.arguments for k, _ in given):
        launch = load_launch_file(Path(path), {k: v for k, v in given
                                               if k in launch.arguments})
    nodes = []
    for node in launch.nodes:
        params: dict[str, Any] = {}
        for file in node.parameters_files:
            params.update(load_params_file(file, node.name, node.namespace))
        params.update(node.parameters)
        nodes.append(replace(node, parameters=params, parameters_files=()))
    return LaunchSpec(launch.name, tuple(nodes), launch.arguments)


class TrialRig:
    """One trial's simulated rig: a fresh rclpy context on ``domain_id``, every node of the
    launch file on a :class:`~cgail_rig.lockstep.LockstepExecutor`, a recorder.

    Args:
        settings: the session's settings.
        spec: the trial.
        domain_id: the ROS domain of the rig.
    """

    def __init__(self, settings: SessionSettings, spec: TrialSpec, domain_id: int) -> None:
        import rclpy
        from rclpy.parameter import Parameter
        from rclpy.signals import SignalHandlerOptions

        from cgail_rig.launcher import build_node, LEAN_PARAMETERS
        from cgail_rig.lockstep import LockstepExecutor

        limit_heap_arenas()  # (before the first rig's middleware starts its threads)
        self.settings, self.spec = settings, spec
        self.context = rclpy.Context()
        rclpy.init(args=ROS_ARGS, context=self.context, domain_id=domain_id,
                   signal_handler_options=SignalHandlerOptions.NO)
        self.nodes: dict[str, Any] = {}
        self.recorder: Any = None
        self._tmp = tempfile.mkdtemp(prefix='cgail_trial_')
        self.executor = LockstepExecutor(
            period_s=1.0 / settings.physics_rate, transport='inprocess',
            sweep_every=max(1, round(SWEEP_S * settings.physics_rate)))
        try:
            launch = rig_launch(str(settings.launch_file or default_launch_file()),
                                (('anatomy', settings.anatomy),
                                 ('policy_path', settings.policy)))
            overrides = self._overrides(Path(self._tmp) / 'aurora')
            autonomy = spec.condition in AUTONOMY_CONDITIONS
            for spec_node in launch.nodes:
                if not {'gui': settings.gui, 'igtl_bridge': settings.igtl,
                        'foxglove_bridge': settings.foxglove, 'autonomy': autonomy,
                        'teleop': not autonomy,
                        'operator': spec.condition not in ('autonomous', 'autonomous-policy'),
                        }.get(spec_node.name, True):
                    continue  # started only when asked for, or in its conditions
                self.nodes[spec_node.name] = build_node(
                    spec_node, overrides.get(spec_node.name, {}), lean=True,
                    context=self.context, prepare=self.executor.add_node)
            self.phantom = self.nodes['phantom']
            self.planner = self.nodes['planner']
            # (None where the condition runs without it)
            self.operator: Any = self.nodes.get('operator')
            self.autonomy: Any = self.nodes.get('autonomy')
            self.executor.add_hook(self.phantom.advance)
            self.session = rclpy.create_node(
                'session', context=self.context, start_parameter_services=False,
                enable_rosout=False, parameter_overrides=[
                    Parameter(k, value=v) for k, v in LEAN_PARAMETERS.items()])
            self.executor.add_node(self.session)
            self._start_recorder()
        except BaseException:
            self.close()
            raise

    def _overrides(self, link: Path) -> dict[str, dict[str, Any]]:
        s, spec = self.settings, self.spec
        control = s.physics_rate / 2.0  # host control loops: every second tick
        autonomy = spec.condition in AUTONOMY_CONDITIONS
        # a fault only where one is injected: the guided conditions' phantom is as it was
        fault = {'fault': spec.fault, 'fault_goal_s': SETTLE_S} if spec.fault else {}
        return {
            'phantom': {'anatomy': s.anatomy, 'mode': s.mode, 'aurora_link': str(link),
                        'lockstep': True, 'seed': spec.seed, 'physics_rate_hz': s.physics_rate,
                        'plant': s.plant, 'plant_seed': s.plant_seed,
                        'start_id': spec.start_id, 'target_id': spec.target_id,
                        'marker_max_triangles': RECORDED_LUMEN_TRIANGLES,
                        'marker_rate_hz': RECORDED_MARKER_RATE_HZ,
                        'lumen_rate_hz': RECORDED_LUMEN_RATE_HZ, **fault},
            # the simulated Aurora answers in the polling thread (em_tracker.hw.aurora's
            # InProcessAurora): no pty round trip and thread switch per frame
            'aurora': {'port': str(link), 'rate_hz': s.tracker_rate, 'poll_mode': 'clock',
                       'link': 'in_process'},
            'pam_controller': {'control_rate_hz': control, **dict(s.pam_parameters)},
            'sleeve_driver': {'control_rate_hz': control},
            # the autonomy tracks the C-GAIL path (the planner's guidance of the cgail condition)
            'planner': {'anatomy': s.anatomy, 'mode': s.mode, 'policy_path': s.policy,
                        'planner_type': 'cgail' if autonomy else spec.condition},
            'operator': {'time_limit_s': s.time_limit, 'seed': spec.seed, 'skill': spec.skill,
                         **({'role': 'supervise'} if spec.condition == 'shared' else {})},
            'autonomy': {'anatomy': s.anatomy, 'mode': s.mode, 'autostart': True,
                         'controller': 'policy' if spec.condition == 'autonomous-policy'
                         else 'path',
                         'policy_path': s.autonomy_policy or s.policy,
                         'autonomy_mode': 'shared' if spec.condition == 'shared'
                         else 'autonomous',
                         'deadman_required': spec.condition == 'shared',
                         'rate_hz': control, 'max_bend': AUTONOMY_MAX_BEND},
            'gui': {'anatomy': s.anatomy, 'dynamic': s.mode == 'dynamic', 'port': s.gui_port},
            'igtl_bridge': {'anatomy': s.anatomy, 'port': s.igtl_port},
            'foxglove_bridge': {'port': s.foxglove_port},
        }

    def _start_recorder(self) -> None:
        from geometry_msgs.msg import PoseStamped

        from cgail_bags.record import BagRecorder, RecorderConfig
        from cgail_planner.nodes import conversions as conv

        self._goal_pub = self.session.create_publisher(PoseStamped, 'planner/goal',
                                                       conv.COMMAND_QOS)
        topics = TOPICS + (AUTONOMY_TOPICS if self.spec.condition in AUTONOMY_CONDITIONS
                           else ())
        self.recorder = BagRecorder(self.session, RecorderConfig(
            output=Path(self.spec.bag), topics=topics, condition=self.spec.condition,
            compress=True))
        # discovery of the rig's own publishers takes wall time, not simulated time
        deadline = time.monotonic() + 30.0
        while len(self.recorder.topics) < len(topics):
            if time.monotonic() > deadline:
                raise RuntimeError(f'expected the recorder to find {list(topics)} within 30 s, '
                                   f'found {self.recorder.topics}')
            time.sleep(0.01)
            self.recorder.discover()
        self.executor.seal()
        # the latched samples published before the recorder subscribed (aurora's /tf_static
        # at configure, the phantom's first markers) reach it asynchronously: wait for them
        # at simulated time 0, or a loaded machine would log them at a later tick
        recorder = self.recorder
        self.executor.settle(lambda: all(recorder.counts.get(t, 0) >= 1
                                         for t in LATCHED_AT_START))

    def publish_goal(self) -> None:
        """Publish the phantom's current target on ``planner/goal``, stamped now."""
        import numpy as np

        from cgail_planner.nodes import conversions as conv

        self._goal_pub.publish(conv.pose_msg(self.session.get_clock().now().to_msg(), 'phantom',
                                             self.phantom.target_position(), np.eye(3)))

    def run(self) -> TrialResult:
        """The trial's protocol; returns its result (the bag is closed by :meth:`close`)."""
        ex = self.executor
        result = TrialResult(self.spec)
        unscheduled_before = ex.stats.unscheduled
        wall0 = time.monotonic()
        pace = self.settings.time_scale

        def tick() -> None:
            ex.tick()
            if pace > 0.0:
                ahead = ex.now_s / pace - (time.monotonic() - wall0)
                if ahead > 0.0:
                    time.sleep(ahead)

        while ex.now_s < SETTLE_S - 1e-9:
            tick()
        if self.planner.last_pose is None:
            result.outcome = f'no tip pose from the tracker within {SETTLE_S} s (simulated)'
            result.failed = True
        else:
            self.publish_goal()
            t0 = ex.now_s
            failed_before = self.planner.counts['failed_plans']
            last_goal = t0
            while not result.outcome:
                tick()
                now = ex.now_s
                if self.phantom.physics_error:
                    # the phantom froze (a deformable wall beyond its bound): the trial ends
                    # here as a counted outcome, its bag kept and evaluated as a failure
                    result.outcome = (f'simulation fault at {now - t0:.1f} s (anatomy '
                                      f'{self.settings.anatomy}, seed {self.spec.seed}): '
                                      f'{self.phantom.physics_error}')
                elif self.autonomy is not None:
                    result.outcome = self._autonomy_outcome(now - t0, failed_before)
                elif self.operator.done:
                    result.outcome = self.operator.operator.reason
                elif self.planner.counts['failed_plans'] > failed_before and \
                        self.planner.follower is None and self.operator.operator.state == 'idle':
                    result.outcome = f'no path: {self.planner.last_error}'
                elif now - t0 > self.settings.time_limit + 5.0:
                    result.outcome = 'time limit (operator still running)'
                if self.settings.mode == 'dynamic' and now - last_goal >= 1.0 - 1e-9:
                    last_goal = now
                    self.publish_goal()
            result.sim_s = ex.now_s - t0
            if self.autonomy is not None:
                self._autonomy_record(result, t0)
            end = ex.now_s + TAIL_S
            while ex.now_s < end - 1e-9:
                tick()
        result.ticks = ex.stats.ticks
        result.unscheduled = ex.stats.unscheduled - unscheduled_before
        result.callback_errors = list(ex.errors)
        return result

    def _autonomy_outcome(self, elapsed: float, failed_before: int) -> str:
        """The end of an autonomy trial ('' while it runs): ``done`` (the controller's arrival,
        the operator's stop rule), ``stopped:<reason>: <message>``, no path, or the limit."""
        autonomy = self.autonomy
        state = autonomy.state
        if state == 'done':
            return str(autonomy.controller.done)
        if state.startswith('stopped') and autonomy.supervisor.stop is not None:
            return f'{state}: {autonomy.supervisor.stop.message}'
        if self.planner.counts['failed_plans'] > failed_before and \
                self.planner.follower is None and state == 'idle':
            return f'no path: {self.planner.last_error}'
        if elapsed >= self.settings.time_limit - 1e-9:
            return f'time limit {self.settings.time_limit:.0f} s reached ({state})'
        return ''

    def _autonomy_record(self, result: TrialResult, t0: float) -> None:
        """The caps measured on the true plant and the fault's detection
        (:class:`FaultRecord`)."""
        from cgail_rig.core.faults import DETECTION_BOUNDS_S, detection_time

        caps = self.phantom.caps
        result.caps = (caps.max_speed, caps.max_bend, caps.max_pressure)
        result.caps_exceeded = caps.exceeded()
        fault = self.phantom.fault
        if fault is None:
            return
        stop = self.autonomy.supervisor.stop
        started = self.phantom.fault_started
        seen = self.phantom.fault_observable_at
        observable = math.nan if seen is None else seen
        result.fault = FaultRecord(
            fault.kind, fault.onset_s - t0 if started else math.nan,
            stop.reason if stop is not None else '',
            detection_time(fault.kind, fault.onset_s if started else math.nan,
                           stop.at if stop is not None else math.nan, observable),
            DETECTION_BOUNDS_S[fault.kind], observable - fault.onset_s)

    def close(self) -> dict[str, int]:
        """Stop recording (the bag is closed), destroy the nodes and the context; returns the
        recorded messages per topic."""
        import rclpy

        counts: dict[str, int] = {}
        if self.recorder is not None:
            self.recorder.stop()
            counts = dict(self.recorder.counts)
            self.recorder = None
        for node in [*reversed(list(self.nodes.values())), getattr(self, 'session', None)]:
            if node is not None:
                node.destroy_node()
        self.nodes.clear()
        for name in ('phantom', 'planner', 'operator', 'autonomy', 'session', 'executor'):
            self.__dict__.pop(name, None)  # the rig is spent: drop its references
        rclpy.try_shutdown(context=self.context)
        # the lifecycle nodes' handles are freed with the last reference to them (cycles): until
        # then the context's participant would still announce aurora/pam_controller/
        # sleeve_driver to the domain (a later refusal check would see "device nodes")
        gc.collect()
        self.context.destroy()
        shutil.rmtree(self._tmp, ignore_errors=True)
        release_freed_heap()
        return counts


def release_freed_heap() -> None:
    """Return the heap a closed rig freed to the OS (glibc's ``malloc_trim``; nothing
    elsewhere).

    glibc keeps freed chunks for reuse and returns only the top of its main heap: after each
    trial the freed messages, bag buffers and middleware entities stayed resident and the next
    trial's allocations landed around them, so a process running trial after trial
    (``bench/bench_autonomy_soak.py``, ``cgail session --jobs 1``) kept ~15 MB more resident
    after 20 trials (glibc's free heap 16 -> 30 MB) while its Python objects, traced
    allocations, glibc's in-use bytes, threads and file descriptors stayed flat. Trimming after
    each trial hands that back (a few ms); the recorded data is unchanged.
    """
    _glibc('malloc_trim', 0)


def _glibc(function: str, *args: int) -> None:
    """Call glibc's allocator ``function`` with ``args`` on Linux; nothing elsewhere, nor where
    the C library has no such function (musl)."""
    if not sys.platform.startswith('linux'):
        return
    import ctypes

    with contextlib.suppress(OSError, AttributeError):
        getattr(ctypes.CDLL(None), function)(*args)


#: glibc heap arenas a process that builds rig after rig may keep (:func:`limit_heap_arenas`).
HEAP_ARENAS = 2


def limit_heap_arenas() -> None:
    """Cap glibc's heap arenas at :data:`HEAP_ARENAS` in this process (``mallopt(M_ARENA_MAX)``;
    nothing elsewhere).

    Each rig starts the middleware's threads afresh, and glibc gives threads arenas of their own,
    up to 8 per core. The freed chunks of each arena stay in it, scattered, so that
    :func:`release_freed_heap` cannot return them: a soak (``bench/bench_autonomy_soak.py
    --detail``) kept 47-50 MB of free heap after 150 trials and went on growing (free heap
    +3.3 MB per 100 trials, RSS +3.2) while the heap in use stayed flat. With two arenas the
    free heap stayed at 19 MB (``MALLOC_ARENA_MAX=2``, same soak). Arenas already made are kept;
    the cap holds for those made after it. A process that runs trials calls it first (``cgail
    session``, its workers, the soak), and every rig again when it is built.
    """
    _glibc('mallopt', -8, HEAP_ARENAS)  # -8: M_ARENA_MAX


def run_trial(settings: SessionSettings, spec: TrialSpec, domain_id: int) -> TrialResult:
    """Build the trial's rig on ``domain_id``, run it, close it; never raises for a rig error
    (the result says ``failed``), only for KeyboardInterrupt."""
    import traceback

    wall0 = time.monotonic()
    rig: TrialRig | None = None
    try:
        rig = TrialRig(settings, spec, domain_id)
        result = rig.run()
    except KeyboardInterrupt:
        raise
    except Exception as exc:
        result = TrialResult(spec, outcome=f'rig error: {type(exc).__name__}: {exc}',
                             failed=True, callback_errors=[traceback.format_exc()])
    finally:
        if rig is not None:
            counts = rig.close()
    if rig is not None:
        result.messages = counts
    result.domain_id = domain_id
    result.wall_s = time.monotonic() - wall0
    return result


def rig_modules(launch_file: str = '') -> None:
    """Import the modules a trial's rig needs (rclpy, the recorder, the lockstep executor, the
    modules of the launch file's nodes), touching no ROS domain: what a process can do while its
    domain probe listens (:func:`~cgail_rig.domain.reserve_domain_during`)."""
    import importlib

    import cgail_bags.record  # noqa: F401
    from cgail_rig.launch_spec import load_launch_file
    import cgail_rig.launcher
    import cgail_rig.lockstep  # noqa: F401

    for spec in load_launch_file(Path(launch_file or default_launch_file())).nodes:
        importlib.import_module(spec.plugin.partition(':')[0])


#: Simulated seconds a warm-up rig runs after its goal (:func:`warm_up`): the planner plans and
#: the operator starts to drive, so every node's code has run once.
WARM_UP_S = 1.0


def warm_up(settings: SessionSettings, spec: TrialSpec, domain_id: int) -> None:
    """Build ``spec``'s rig on ``domain_id`` with its bag in a temporary directory, run it a
    moment past its goal (:data:`WARM_UP_S`), and throw it away.

    A process's first trial cost ~2 s more than the next ones (the nodes' imports, the ONNX
    policy's session, the numba kernels loaded from their cache, first calls): a worker of
    :class:`Workers` pays that while the session identifies the PAM model, instead of in
    its first trial. What a trial records does not depend on what ran before it in its process
    (module docstring), so the trials are those of a cold worker.
    """
    from dataclasses import replace

    with tempfile.TemporaryDirectory(prefix='cgail_warm_up_') as tmp:
        rig = TrialRig(settings, replace(spec, bag=str(Path(tmp) / 'bag')), domain_id)
        try:
            ex = rig.executor
            while ex.now_s < SETTLE_S - 1e-9:
                ex.tick()
            rig.publish_goal()
            end = ex.now_s + WARM_UP_S
            while ex.now_s < end - 1e-9:
                ex.tick()
        finally:
            rig.close()


# ---------------------------------------------------------------------- worker processes
_WORKER: dict[str, Any] = {}


def _worker_init(log_dir: str, warm: tuple[SessionSettings, TrialSpec] | None = None,
                 gate: Any = None) -> None:
    """A worker: Ctrl-C is the parent's to handle; a domain of its own (the rig's modules
    imported while it is probed); logs to ``log_dir``; with ``warm``, :func:`warm_up` on it;
    all that while holding ``gate`` (a semaphore: :class:`Workers`); then what it holds frozen
    for the garbage collector (``gc.freeze``)."""
    from cgail_rig.domain import reserve_domain_during

    limit_heap_arenas()  # (before the domain probe's middleware threads)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ['ROS_LOG_DIR'] = log_dir
    launch_file = warm[0].launch_file if warm is not None else ''
    with gate if gate is not None else contextlib.nullcontext():
        _WORKER['lease'], _ = reserve_domain_during(lambda: rig_modules(launch_file), env={})
        if warm is not None:
            with contextlib.suppress(Exception):  # (the trials themselves report what fails)
                warm_up(*warm, _WORKER['lease'].domain_id)
        # what the worker holds from now on (modules, caches, the policy's session: ~216k
        # objects) is never garbage: out of the collector's sight, each trial's gc.collect()
        # (TrialRig.close) scans that trial's objects only, 6 ms instead of 80 ms
        gc.collect()
        gc.freeze()


def _worker_ready() -> int:
    return os.getpid()


def _worker_run(settings: SessionSettings, spec: TrialSpec) -> TrialResult:
    return run_trial(settings, spec, _WORKER['lease'].domain_id)


class Workers:
    """``jobs`` worker processes for :func:`run_trials` (:attr:`pool`), started now: each
    reserves a domain of its own and, with ``warm`` (settings and a trial), warms up
    (:func:`warm_up`).

    Started before the trials are known (``cgail session`` starts them before it identifies the
    PAM model, which the trials' settings need), they spend the identification on their own
    start (Python and the rig's imports, the domain probe, the first rig: ~4 s of a core each)
    instead of delaying their first trials. ``hold`` of them wait to start until
    :meth:`release`: while this process identifies the model on one core, the workers starting
    at once on the others leave it that core (on 2 cores, two workers starting beside it would
    slow the identification, which every trial waits for, by a third).

    Args:
        jobs: worker processes.
        log_dir: ``ROS_LOG_DIR`` of the workers.
        warm: ``(settings, spec)`` of the warm-up rig; None: no warm-up.
        hold: workers that start only after :meth:`release` (0..jobs-1).
    """

    def __init__(self, jobs: int, log_dir: Path,
                 warm: tuple[SessionSettings, TrialSpec] | None = None, hold: int = 0) -> None:
        ctx = multiprocessing.get_context('spawn')
        self._gate = ctx.Semaphore(jobs)
        self._held = max(0, min(hold, jobs - 1))
        for _ in range(self._held):
            self._gate.acquire()
        self.pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=jobs, mp_context=ctx, initializer=_worker_init,
            initargs=(str(log_dir), warm, self._gate))
        # a pool that spawns its processes starts one per task submitted while none is idle
        for _ in range(jobs):
            self.pool.submit(_worker_ready)

    def release(self) -> None:
        """Let the held workers start (idempotent)."""
        while self._held:
            self._held -= 1
            self._gate.release()

    def shutdown(self) -> None:
        """Release the held workers and wait for the pool to end (pending tasks cancelled)."""
        self.release()
        self.pool.shutdown(wait=True, cancel_futures=True)


def run_trials(settings: SessionSettings, specs: Sequence[TrialSpec], *, jobs: int,
               domain_id: int | None, log_dir: Path,
               on_result: Callable[[TrialResult], None],
               pool: concurrent.futures.ProcessPoolExecutor | None = None,
               while_running: Sequence[Callable[[], Any]] = ()) -> list[TrialResult]:
    """Run ``specs``: in this process on ``domain_id`` (``jobs == 1``), or in ``jobs`` worker
    processes with a domain each (``pool``: those of :class:`Workers`, shut down here; else
    started here). ``on_result`` sees each result as it completes; the list comes back in
    ``specs`` order. ``while_running`` are called in this process once the trials are handed to
    the workers (before them with ``jobs == 1``). Ctrl-C stops early: the finished trials come
    back."""
    results: dict[TrialSpec, TrialResult] = {}
    if jobs == 1:
        assert domain_id is not None
        try:
            for work in while_running:
                work()
            for spec in specs:
                results[spec] = run_trial(settings, spec, domain_id)
                on_result(results[spec])
        except KeyboardInterrupt:
            pass
        return [results[s] for s in specs if s in results]
    if pool is None:
        pool = Workers(jobs, log_dir).pool
    try:
        futures = {pool.submit(_worker_run, settings, spec): spec for spec in specs}
        for work in while_running:
            work()
        for future in concurrent.futures.as_completed(futures):
            spec = futures[future]
            try:
                results[spec] = future.result()
            except Exception as exc:
                results[spec] = TrialResult(spec, outcome=f'worker error: {exc}', failed=True)
            on_result(results[spec])
    except KeyboardInterrupt:
        pass
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
    return [results[s] for s in specs if s in results]


# ---------------------------------------------------------------------- command line
def build_parser() -> argparse.ArgumentParser:
    """Command-line options of ``cgail session``."""
    p = tool_parser('session', __doc__)
    p.add_argument('--trials', type=int, default=30,
                   help='trials per condition (default 30, the power the comparison needs: at '
                        "the paper's 10 no difference between the conditions was significant; "
                        'paper: 10)')
    p.add_argument('--pretrain', type=int, default=10,
                   help="the operator's pre-training trials per condition before the measured "
                        'ones (paper: 10); modelled by its skill, not run')
    p.add_argument('--anatomy', default='default',
                   help="built-in anatomy name ('default', 'elongated'), prepared anatomy "
                        'directory or mesh file with its <stem>.yaml landmarks (a path needs '
                        '--policy for the cgail condition)')
    p.add_argument('--mode', choices=('static', 'dynamic'), default='static',
                   help='rigid phantom or deformable beating wall')
    p.add_argument('--out', type=Path, default=Path('runs/invitro_session'),
                   help='output directory (bags/, logs/, metrics.md, metrics.csv, box plots)')
    p.add_argument('--policy', type=Path, default=None,
                   help='ONNX C-GAIL policy (cgail export-onnx); default: the committed '
                        'cgail_planner/models/cgail_<anatomy>_<mode>.onnx (static if there is no '
                        'policy for the mode)')
    p.add_argument('--conditions', nargs='+', choices=ALL_CONDITIONS, default=list(CONDITIONS),
                   help="conditions to run, in order: the guided 'cgail' and 'centerline' (the "
                        "scripted operator drives teleop), and the autonomy's (autonomy_node "
                        "drives along the C-GAIL path under its supervisor): 'autonomous' (path "
                        "tracker), 'autonomous-policy' (the ONNX policy controller, --policy), "
                        "'shared' (path tracker; the operator holds the deadman and corrects "
                        'beyond 5 mm from the path)')
    p.add_argument('--faults', nargs='+', choices=FAULT_KINDS, default=[],
                   help='inject one fault per trial of the autonomy conditions, trial k the '
                        'k-th of these in turn, its onset 3-8 simulated s after the goal drawn '
                        'from the trial seed (cgail_rig.core.faults); the report gives each '
                        "fault's detection time and flags a miss")
    p.add_argument('--jobs', type=int, default=None,
                   help='worker processes running trials in parallel (default: the number of '
                        'CPUs); the results do not depend on it')
    p.add_argument('--time-scale', type=float, default=None,
                   help='at most this many simulated seconds per wall second (default: as '
                        'fast as the CPU allows; 1 with --gui)')
    p.add_argument('--time-limit', type=float, default=180.0,
                   help='trial time limit, simulated s (paper: 180)')
    p.add_argument('--physics-rate', type=float, default=40.0,
                   help='lockstep tick rate: phantom physics and simulated devices, Hz of '
                        'simulated time (default 40: one tick per Aurora frame; the pam and '
                        'sleeve-driver control loops run at half of it)')
    p.add_argument('--tracker-rate', type=float, default=40.0,
                   help='EM tracker frame rate in simulated time, Hz (the Aurora: 40)')
    p.add_argument('--launch-file', type=Path, default=None,
                   help="rig launch YAML (default: the package's sim_rig.launch.yaml)")
    p.add_argument('--seed', type=int, default=0,
                   help='session seed: the true plant (one catheter for the session) and each '
                        "trial's own seed (EM and stick noise)")
    p.add_argument('--gui', action='store_true',
                   help='also start the guidance GUI (gui_node) and print its URL (one trial '
                        'at a time, paced at --time-scale 1 unless given)')
    p.add_argument('--gui-port', type=int, default=8780, help='port of the guidance GUI')
    p.add_argument('--igtl', action='store_true',
                   help='also start igtl_bridge: 3D Slicer follows the trial over OpenIGTLink '
                        '(one trial at a time)')
    p.add_argument('--igtl-port', type=int, default=18944,
                   help="port of igtl_bridge (Slicer's default 18944)")
    p.add_argument('--foxglove', action='store_true',
                   help='also start foxglove_bridge: the Foxglove app follows the trial live '
                        'over ws://127.0.0.1:<port> (one trial at a time)')
    p.add_argument('--foxglove-port', type=int, default=8765,
                   help="port of foxglove_bridge (Foxglove's default 8765)")
    p.add_argument('--plant', choices=PLANTS, default='identified',
                   help="default 'identified', as a rig team runs it; 'nominal': the "
                        "phantom's true plant (its own actuator model, drawn from sourced "
                        'ranges with --seed) and the PAM controller with its '
                        "nominal model; 'identified': the same plant, and the controller with "
                        'the model cgail identify-pam identified on it (run first on the '
                        "simulated bench, cached in <out>/identification/); 'ideal': the plant "
                        "is the controller's own nominal model (for comparison)")
    return p


def autonomy_report(results: Sequence[TrialResult]) -> list[str]:
    """Markdown of the autonomy conditions' trials ([] without any): the end states per
    condition, the injected faults (caught within the stated bound, flagged MISSED, or for a
    stuck PAM never observable; detection time median and max per kind; for stuck_pam the
    delay from the onset until it became observable) and the caps measured on the true
    plant."""
    from cgail_rig.core.faults import Caps, DETECTION_BOUNDS_S

    rows = [r for r in results if r.spec.condition in AUTONOMY_CONDITIONS and not r.failed]
    if not rows:
        return []
    lines = ['', '## Autonomy: end states', '',
             '| condition | trials | done | stopped (reason: count) | time limit / other |',
             '|---|---:|---:|---|---:|']
    for condition in AUTONOMY_CONDITIONS:
        mine = [r for r in rows if r.spec.condition == condition]
        if not mine:
            continue
        done = sum(not r.outcome.startswith(('stopped:', 'time limit', 'no path',
                                             'simulation fault')) for r in mine)
        reasons: dict[str, int] = {}
        for r in mine:
            if r.outcome.startswith('stopped:'):
                key = r.outcome.split(':')[1]
                reasons[key] = reasons.get(key, 0) + 1
        stopped = ', '.join(f'{k}: {n}' for k, n in sorted(reasons.items())) or '-'
        other = len(mine) - done - sum(reasons.values())
        lines.append(f'| {condition} | {len(mine)} | {done} | {stopped} | {other} |')
    faulted = [r for r in rows if r.fault is not None]
    if faulted:
        import numpy as np

        lines += ['', '## Autonomy: injected faults', '',
                  'Detection time: fault onset to the supervisor\'s stop, simulated s; for '
                  'stuck_pam from the moment the stuck chamber became observable (its setpoint '
                  'off the held pressure by more than 20 kPa for 0.5 s: until then nothing '
                  'tells it from a healthy one), 0 for a stop after the onset but before. A '
                  'fault is caught when the supervisor stopped so within the stated bound '
                  '(docs/guides/autonomy.md); a stuck PAM never observable before the trial '
                  'ended, and not stopped, is counted apart (never observable: neither caught '
                  'nor missed); anything else is flagged MISSED.', '',
                  '| fault | injected | caught | detection median (s) | detection max (s) | '
                  'bound (s) | stop reasons | missed | never observable | onset to observable, '
                  'median / max (s) |', '|---|---:|---:|---:|---:|---:|---|---|---:|---|']
        for kind in FAULT_KINDS:
            mine = [r for r in faulted if r.fault is not None and r.fault.kind == kind]
            if not mine:
                continue
            records = [r.fault for r in mine if r.fault is not None]
            injected = [f for f in records if f.injected]
            caught = [f for f in injected if f.caught]
            times = np.array([f.detection_s for f in injected if f.detection_s == f.detection_s])
            reasons_seen = sorted({f.stop_reason for f in injected if f.stop_reason})
            missed = [r.spec.label for r in mine if r.fault is not None and r.fault.missed]
            never, seen = '-', '-'
            if kind == 'stuck_pam':
                never = str(sum(f.never_observable for f in injected))
                delays = np.array([f.observable_s for f in injected
                                   if f.observable_s == f.observable_s])
                seen = f'{np.median(delays):.3f} / {delays.max():.3f}' if len(delays) else \
                    'never'
            lines.append(
                f'| {kind} | {len(injected)}/{len(mine)} | {len(caught)} | '
                f'{np.median(times) if len(times) else math.nan:.3f} | '
                f'{times.max() if len(times) else math.nan:.3f} | '
                f'{DETECTION_BOUNDS_S[kind]:g} | {", ".join(reasons_seen) or "-"} | '
                f'{"**MISSED: " + ", ".join(missed) + "**" if missed else "none"} | '
                f'{never} | {seen} |')
        late = [r.spec.label for r in faulted if r.fault is not None and not r.fault.injected]
        if late:
            lines += ['', f'Trials that ended before their fault\'s onset (not counted): '
                      f'{", ".join(late)}.']
    caps = Caps()
    worst = [max(r.caps[i] for r in rows) for i in range(3)]
    exceeded = [f'{r.spec.label}: {"; ".join(r.caps_exceeded)}' for r in rows
                if r.caps_exceeded]
    lines += ['', '## Autonomy: caps on the true plant', '',
              'Measured in the phantom on every physics step of every autonomy trial (the tip\'s '
              'advance, the plant\'s bend, the regulators\' chamber pressures), not on the '
              'commands.', '',
              '| quantity | largest measured | cap |', '|---|---:|---:|',
              f'| tip advance speed (mm/s) | {worst[0] * 1e3:.3f} | '
              f'{caps.max_insertion_speed * 1e3:.3f} |',
              f'| bend (rad) | {worst[1]:.3f} | {caps.max_bend:.3f} |',
              f'| chamber pressure (kPa) | {worst[2] / 1e3:.1f} | '
              f'{caps.max_pressure_pa / 1e3:.1f} |', '',
              'Caps exceeded: ' + ('**' + ' | '.join(exceeded) + '**' if exceeded else 'none.')]
    return lines


def identification_cached(directory: Path, plant_seed: int) -> bool:
    """Whether ``<directory>/plant_seed_<seed>/pam_identified.yaml`` holds a model of every key
    of ``IDENTIFIED_KEYS`` (else :func:`identified_pam_parameters` identifies it: none yet, or
    one of an older model)."""
    import yaml

    from pam_controller.core.identification import IDENTIFIED_KEYS

    path = directory / f'plant_seed_{plant_seed}' / 'pam_identified.yaml'
    cached = yaml.safe_load(path.read_text())['pam_controller']['ros__parameters'] \
        if path.is_file() else {}
    return set(IDENTIFIED_KEYS) <= set(cached)


def identified_pam_parameters(directory: Path, plant_seed: int,
                              log: Callable[[str], None], *, domain_id: int | None = None,
                              plots: list[Callable[[], Path]] | None = None
                              ) -> tuple[tuple[str, float], ...]:
    """The pam_controller model identified on the true plant of ``plant_seed``: read from
    ``<directory>/plant_seed_<seed>/pam_identified.yaml``, after running ``identify_pam``'s
    simulated bench there if it is not cached yet (or was identified for an older model, without
    every key of ``IDENTIFIED_KEYS``), on ``domain_id`` (None: a free domain of its own).
    ``plots``: as :func:`cgail_rig.identify_pam.identify_bag` (``loops.png`` drawn later)."""
    import yaml

    from cgail_rig.identify_pam import identify_sim
    from pam_controller.core.identification import IDENTIFIED_KEYS

    where = directory / f'plant_seed_{plant_seed}'
    path = where / 'pam_identified.yaml'
    if not identification_cached(directory, plant_seed):
        log(f'cgail session: identifying the PAM model on plant seed {plant_seed} '
            f'(cgail identify-pam --sim, {where})')
        t0 = time.monotonic()
        result = identify_sim(where, plant_seed=plant_seed, domain_id=domain_id, plots=plots)
        e = result.errors
        log(f'cgail session: RMS bend error nominal {e["nominal"]["all"]:.4f} rad, identified '
            f'{e["identified"]["all"]:.4f} rad ({time.monotonic() - t0:.0f} s)')
    values = yaml.safe_load(path.read_text())['pam_controller']['ros__parameters']
    return tuple((key, float(values[key])) for key in IDENTIFIED_KEYS)


def _clock(seconds: float) -> str:
    """``m:ss`` of a duration in seconds."""
    m, s = divmod(round(max(0.0, seconds)), 60)
    return f'{m}:{s:02d}'


def progress(done: int, total: int, elapsed_s: float, trials_s: float) -> str:
    """``elapsed m:ss, about m:ss left``: the command's elapsed wall time, and the trials left
    at the pace of those done so far (``trials_s``: wall seconds since the first trial
    started)."""
    left = trials_s / done * (total - done) if done else 0.0
    return f'elapsed {_clock(elapsed_s)}, about {_clock(left)} left'


def _trial_line(done: int, total: int, r: TrialResult, pace: str = '') -> str:
    s = r.spec
    extra = ''
    if r.callback_errors:
        extra += f'  {len(r.callback_errors)} callback error(s), see logs/'
    if r.unscheduled:
        extra += f'  {r.unscheduled} message(s) from outside the rig'
    return (f'[{done:{len(str(total))}d}/{total}] {s.label:<14} start {s.start_id} target '
            f'{s.target_id}  {r.outcome:<38} T {r.sim_s:6.1f} s  ({r.wall_s:5.1f} s wall, '
            f'domain {r.domain_id}){"  " + pace if pace else ""}{extra}')


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``cgail session``; returns the exit status."""
    from cgail_rig.domain import DomainError, requested_domain, reserve_domain_during

    args = build_parser().parse_args(argv)
    limit_heap_arenas()  # (before any middleware thread of this process)
    t_command = time.monotonic()

    def fail(text: str) -> int:
        print(f'cgail session: error: {text}', file=sys.stderr)
        return 2

    if args.trials < 1:
        return fail(f'--trials must be >= 1, found {args.trials}')
    if args.pretrain < 0:
        return fail(f'--pretrain must be >= 0, found {args.pretrain}')
    if args.jobs is not None and args.jobs < 1:
        return fail(f'--jobs must be >= 1, found {args.jobs}')
    if args.time_scale is not None and not args.time_scale >= 0.0:
        return fail(f'--time-scale must be >= 0 (0: as fast as possible), found '
                    f'{args.time_scale}')
    if not 1.0 <= args.physics_rate <= 1000.0:
        return fail(f'--physics-rate must be in [1, 1000] Hz, found {args.physics_rate}')
    if not os.environ.get('ROS_AUTOMATIC_DISCOVERY_RANGE'):
        return fail('ROS_AUTOMATIC_DISCOVERY_RANGE is unset (DDS would multicast); run through '
                    'scripts/ws')
    from cgail_sim.anatomy import AnatomyError
    from cgail_sim.anatomy_spec import anatomy_label, is_builtin, is_named
    from cgail_sim.worlds import load_world

    builtin = is_builtin(args.anatomy)
    try:  # one line for a bad anatomy, and the caches (centerlines) warm before the workers
        load_world(args.anatomy)
    except AnatomyError as exc:
        return fail(str(exc))
    # (a name travels as it is; a path, absolute, to the workers and nodes)
    anatomy = args.anatomy if is_named(args.anatomy) else str(
        Path(args.anatomy).expanduser().resolve())
    label = anatomy_label(args.anatomy)
    needs_policy = sorted({'cgail', *AUTONOMY_CONDITIONS} & set(args.conditions))
    if args.faults and not set(AUTONOMY_CONDITIONS) & set(args.conditions):
        return fail(f'--faults: expected an autonomy condition {AUTONOMY_CONDITIONS} in '
                    f'--conditions, found {args.conditions}')
    if args.policy is None and needs_policy and not builtin:
        return fail(f'the cgail condition needs --policy <model.onnx> for anatomy {anatomy}: '
                    f'expected a policy trained on it (there is a committed one only for the '
                    f'built-in anatomies), found no --policy')
    if args.policy is None and builtin:
        args.policy = default_policy(args.anatomy, args.mode)
    if needs_policy and not args.policy.is_file():
        return fail(f'the {needs_policy[0]} condition needs --policy <model.onnx> (cgail '
                    f'export-onnx), found no file at {args.policy}')
    bags_dir = args.out / 'bags'
    if bags_dir.exists() and any(bags_dir.iterdir()):
        return fail(f'{bags_dir} already holds bags; choose another --out')
    try:
        user_domain = requested_domain()
    except DomainError as exc:
        return fail(str(exc))
    specs = plan_trials(args.conditions, args.trials, args.seed, bags_dir,
                        pretrain=args.pretrain, faults=tuple(args.faults))
    jobs = args.jobs or os.cpu_count() or 1
    jobs = max(1, min(jobs, len(specs)))
    notes = []
    for flag, on in (('--gui', args.gui), ('--igtl', args.igtl), ('--foxglove', args.foxglove)):
        if on and jobs > 1:
            jobs = 1
            notes.append(f'{flag}: one trial at a time')
    if user_domain is not None and jobs > 1:
        jobs = 1
        notes.append(f'ROS_DOMAIN_ID={user_domain} is set: one trial at a time on it (unset it '
                     f'to run trials in parallel on free domains)')
    time_scale = args.time_scale if args.time_scale is not None else (1.0 if args.gui else 0.0)
    settings = SessionSettings(
        anatomy=anatomy, mode=args.mode, policy=str(args.policy or ''),
        time_limit=args.time_limit, physics_rate=args.physics_rate,
        tracker_rate=args.tracker_rate, launch_file=str(args.launch_file or ''),
        time_scale=time_scale, gui=args.gui, gui_port=args.gui_port, igtl=args.igtl,
        igtl_port=args.igtl_port, foxglove=args.foxglove, foxglove_port=args.foxglove_port,
        plant='ideal' if args.plant == 'ideal' else 'true', plant_seed=args.seed)
    log_dir = (args.out / 'logs').resolve()
    log_dir.mkdir(parents=True, exist_ok=True)
    os.environ['ROS_LOG_DIR'] = str(log_dir)

    def log(text: str) -> None:
        print(text, flush=True)

    # The workers start first (their imports, domain probes and a warm-up rig with the nominal
    # PAM model, on the other core) while this process identifies the PAM model; one trial at a
    # time: this process's domain, which the identification's bench uses too.
    lease = None
    workers = None
    if jobs == 1:
        try:
            lease, _ = reserve_domain_during(lambda: rig_modules(settings.launch_file))
        except DomainError as exc:
            return fail(str(exc))
        where = f'ROS domain {lease.domain_id} ({lease.source})'
    else:
        # while this process identifies the model on a core, workers start on the others
        identifying = args.plant == 'identified' and not identification_cached(
            args.out / 'identification', args.seed)
        cpus = len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else \
            (os.cpu_count() or 1)
        workers = Workers(jobs, log_dir, warm=(settings, specs[0]),
                          hold=jobs - max(1, cpus - 1) if identifying else 0)
        where = f'{jobs} worker processes, each on a free ROS domain of its own'
    plots: list[Callable[[], Path]] = []
    t_identify = time.monotonic()
    try:
        if args.plant == 'identified':
            settings = dataclasses.replace(settings, pam_parameters=identified_pam_parameters(
                args.out / 'identification', args.seed, log,
                domain_id=lease.domain_id if lease else None, plots=plots))
    except BaseException as exc:
        if workers is not None:
            workers.shutdown()
        if lease is not None:
            lease.release()
        if isinstance(exc, (OSError, ValueError, RuntimeError)):  # bag, fit, domain, bench
            return fail(f'identification of plant seed {args.seed} failed: {exc}')
        raise
    if workers is not None:
        workers.release()
    t_start = time.monotonic()
    log(f'cgail session: {len(specs)} trials ({", ".join(args.conditions)}; '
        f'{label}, {args.mode}) on {where}; policy {args.policy or "-"}; node logs in '
        f'{log_dir}' + ''.join(f'; {n}' for n in notes))
    if args.gui:
        log(f'cgail session: guidance GUI on http://127.0.0.1:{args.gui_port}/ while a trial '
            f'runs')
    if args.igtl:
        log(f'cgail session: OpenIGTLink server on 127.0.0.1:{args.igtl_port} while a trial '
            f'runs (3D Slicer: OpenIGTLinkIF, a client connector to that port)')
    if args.foxglove:
        log(f'cgail session: Foxglove WebSocket on ws://127.0.0.1:{args.foxglove_port} while a '
            'trial runs (Foxglove: Open connection, Foxglove WebSocket; layout '
            'src/cgail_rig/config/foxglove/cgail_layout.json)')
    done = [0]
    # each trial's bag is evaluated as it comes in, while the other trials run, instead of all
    # at the end (~0.1 s of a core each: 5 s for the main job's 60)
    evaluated: dict[tuple[str, str], tuple[list[Any], str]] = {}

    def on_result(result: TrialResult) -> None:
        done[0] += 1
        now = time.monotonic()
        log(_trial_line(done[0], len(specs), result,
                        progress(done[0], len(specs), now - t_command, now - t_start)))
        bag = Path(result.spec.bag)
        if bag.is_dir():
            with contextlib.suppress(Exception):  # (then the report evaluates it, as it would)
                evaluated[(bag.parent.name, bag.name)] = evaluate_trial_bag(bag)

    def draw_plots() -> None:
        for draw in plots:
            try:
                draw()
            except Exception as exc:  # (a figure: the trials go on)
                log(f'cgail session: could not draw the identification\'s figure: {exc}')

    try:
        results = run_trials(settings, specs, jobs=jobs,
                             domain_id=lease.domain_id if lease else None, log_dir=log_dir,
                             on_result=on_result, pool=workers.pool if workers else None,
                             while_running=[draw_plots])
    finally:
        if lease is not None:
            lease.release()
    t_trials = time.monotonic()
    wall_s = t_trials - t_start
    if len(results) < len(specs):
        log(f'cgail session: interrupted after {len(results)} of {len(specs)} trials; '
            f'evaluating those')
    errors = sum(len(r.callback_errors) for r in results)
    if errors:
        (log_dir / 'callback_errors.txt').write_text(
            '\n'.join(f'--- {r.spec.label}\n{e}' for r in results for e in r.callback_errors))
    outcomes = [(r.spec.condition, r.spec.index + 1, r.outcome) for r in results]
    code = report(args.out, bags_dir, outcomes, log, wall_s=wall_s, callback_errors=errors,
                  jobs=jobs, results=results, evaluated=evaluated)
    t_end = time.monotonic()
    log(f'cgail session: {len(results)} trials in {_clock(wall_s)} on {jobs} worker(s); '
        f'{_clock(t_end - t_command)} in all')
    log(f'cgail session: phases: start {t_identify - t_command:.1f} s, identification '
        f'{t_start - t_identify:.1f} s, trials {wall_s:.1f} s, report {t_end - t_trials:.1f} s')
    return code if all(not r.failed for r in results) else max(code, 1)


def success_over_every_trial(trials: Sequence[Any], outcomes: Sequence[tuple[str, int, str]]
                             ) -> list[str]:
    """Markdown: per condition, the success rate over every trial that ran, a trial without
    metrics (no path planned, an unreadable bag) counted as a failure, with its Wilson
    interval. The conditions table beside it rates the evaluable trials only."""
    from cgail_planner.core.metrics import wilson_interval

    ran: dict[str, int] = {}
    for condition, _, _ in outcomes:
        ran[condition] = ran.get(condition, 0) + 1
    lines = ['', '## Success over every trial (a trial without metrics is a failure)', '',
             '| condition | trials run | evaluable | successes | success [95 % Wilson] |',
             '|---|---:|---:|---:|---|']
    for condition in sorted(ran):
        members = [m for m in trials if m.condition == condition]
        wins = sum(bool(m.success) for m in members)
        n = ran[condition]
        lo, hi = wilson_interval(wins, n)
        lines.append(f'| {condition} | {n} | {len(members)} | {wins} | {100 * wins / n:.0f} % '
                     f'[{100 * lo:.0f}-{100 * hi:.0f}] |')
    return lines


def evaluate_trial_bag(bag: Path) -> tuple[list[Any], str]:
    """``(metrics, '')`` of a trial's bag (``cgail bag metrics``, its condition the name of the
    directory it sits in), or ``([], why)`` when it has none (unreadable, no path planned)."""
    from cgail_bags.errors import BagError
    from cgail_bags.metrics_cli import evaluate_bags
    from cgail_planner.core.metrics import MetricsError

    try:
        return evaluate_bags([bag], condition=bag.parent.name), ''
    except (BagError, MetricsError) as exc:
        return [], str(exc)


def report(out: Path, bags_dir: Path, outcomes: list[tuple[str, int, str]],
           log: Callable[[str], None], wall_s: float, callback_errors: int = 0,
           jobs: int = 1, results: Sequence[TrialResult] = (),
           evaluated: Mapping[tuple[str, str], tuple[list[Any], str]] | None = None) -> int:
    """Metrics of every evaluable trial bag: markdown table, CSV, box plots; with the trials
    of autonomy conditions among ``results``, their end states, the injected faults'
    detection and the caps (:func:`autonomy_report`). ``evaluated``: bags already evaluated
    (:func:`evaluate_trial_bag`), by ``(condition directory, bag name)``; the others are
    evaluated here."""
    from cgail_bags.report import box_plots, markdown_report, write_csv
    from cgail_planner.core.metrics import kruskal_by_condition

    trials = []
    skipped = []
    for bag in sorted(p for p in bags_dir.glob('*/*') if p.is_dir()):
        got = (evaluated or {}).get((bag.parent.name, bag.name))
        metrics, why = got if got is not None else evaluate_trial_bag(bag)
        trials += metrics
        if why:
            skipped.append(f'{bag.name}: {why}')
    if not trials:
        log('cgail session: no trial could be evaluated')
        for s in skipped:
            log(f'  {s}')
        return 1
    tests = kruskal_by_condition(trials)
    text = markdown_report(trials, tests)
    faults = sum(o.startswith('simulation fault') for _, _, o in outcomes)
    lines = ['# Simulated in-vitro session', '',
             f'{len(outcomes)} trials, {wall_s:.0f} s wall time ({jobs} job(s)), callback '
             f'errors: {callback_errors}, simulation faults: {faults} (a trial a fault ended '
             'counts as a failure).', '', '## Outcomes', '',
             '| trial | condition | operator outcome |', '|---|---|---|']
    lines += [f'| {k} | {c} | {o} |' for c, k, o in outcomes]
    if skipped:
        lines += ['', '## Trials without metrics', ''] + [f'- {s}' for s in skipped]
    every = success_over_every_trial(trials, outcomes)
    lines += every
    autonomy = autonomy_report(results)
    out.mkdir(parents=True, exist_ok=True)
    (out / 'metrics.md').write_text('\n'.join(lines) + '\n\n' + text
                                    + ''.join(f'\n{line}' for line in autonomy))
    write_csv(trials, out / 'metrics.csv')
    png = box_plots(trials, tests, out / 'metrics_boxplot.png')
    log(text)
    for line in [*every, *autonomy]:
        log(line)
    log(f'cgail session: wrote {out / "metrics.md"}, {out / "metrics.csv"} and {png} '
        f'({wall_s:.0f} s wall)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
