"""The simulated phantom's physics: a follow-the-leader catheter driven by the rig's actuators.

Pure numpy (with the simulator's wall); no rclpy. :mod:`cgail_rig.nodes.phantom_node` feeds
it the catheter's position at the sleeve driver's gripper and the bend its true plant
(:mod:`cgail_rig.core.plant`) makes of the regulator pressures, and sends the resulting tip
pose to the simulated Aurora.

* **Insertion.** The catheter body is a :class:`~cgail_sim.ftl_model.CatheterBatch`
  chain. An insertion increase ``dl`` advances the tip along its heading in sub-steps of
  at most ``max_substep``; a decrease retracts it along its own body (follow-the-leader).
  A change faster than the driver's cap (``max_insertion_speed * dt + max_jump``) is a
  re-homed driver (its position restarted), counted in ``insertion_jumps``, not motion.
  With a plant, ``dl`` is what the plant's slip and backlash leave of the gripper's advance
  (:meth:`~cgail_rig.core.plant.CatheterPlant.advance`, under the last contact's load);
  without one, the tip advances as the given position.
* **Bend.** The bend ``(alpha, gamma)`` (rad) is the bend of the whole steerable
  segment, an arc of constant curvature ``|bend| / L``: per inserted ``dl`` the heading turns by
  ``alpha dl / L`` about ``x_A`` and ``gamma dl / L`` about ``z_A``
  (:func:`cgail_sim.ftl_model.segment_bend_step`), so the tip curves only while it
  advances. The kinematics are the catheter model's (:mod:`cgail_sim.ftl_model`, its
  batched form with one row): the phantom and the simulator move a catheter the same way.
* **Wall.** After each step the tip sphere (catheter radius) is tested against the wall (static,
  or the deformable wall stepped with the heartbeat and the body): a penetrating tip is pushed
  back into the lumen along the wall normal and its heading loses its outward component (it slides
  along the wall). With a plant, the compliant tip also turns away from the wall, inwards by
  the plant's :meth:`~cgail_rig.core.plant.CatheterPlant.tip_deflection` (bounded), and the
  contact's load slows the next insertion. ``contacts`` counts those events.
* **Target.** Attached to a wall particle: in dynamic mode it moves with the wall.
* **Bench fixture** (``fixture: 'bench'``, for ``identify_pam``). The catheter is clamped at
  the base of its steerable segment, in free air, as a rig team identifies the actuators: the
  base is the start pose, the insertion is ignored, there is no wall, and the tip is the base
  composed with the constant-curvature arc of the plant's current bend
  (:func:`bench_tip_pose`: the catheter model's own kinematics, the segment inserted ``L`` at
  that bend). So the EM orientation shows the bend without any advance.
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from cgail_planner.core.rotations import rotate_onto
from cgail_rig.core.plant import Plant
from cgail_sim.ftl_model import (
    advance_pose_steps,
    bend_rotation,
    CatheterBatch,
    CatheterConfig,
    segment_bend_step,
)
from cgail_sim.wall import DeformableWall

FloatArray = NDArray[np.float64]

#: Fixtures of the phantom: ``'none'`` (the catheter in the aorta) or ``'bench'`` (clamped at
#: the base of the steerable segment, in free air).
FIXTURES = ('none', 'bench')


def bench_tip_pose(position: FloatArray, rotation: FloatArray, bend: tuple[float, float],
                   catheter: CatheterConfig, max_step: float) -> tuple[FloatArray, FloatArray]:
    """Tip pose of a segment clamped at ``(position, rotation)`` and bent by ``bend`` (rad).

    The catheter model's constant-curvature arc: the segment's length ``L`` inserted from the
    base in equal steps of at most ``max_step`` at the step bends of
    :func:`~cgail_sim.ftl_model.segment_bend_step` (the bend saturates at
    ``theta_max``), each by :func:`~cgail_sim.ftl_model.advance_pose` (the n steps at one bend:
    :func:`~cgail_sim.ftl_model.advance_pose_steps`, the same bits). The tip's
    rotation relative to the base is the rotation vector ``(alpha, ~0, gamma)``: the product
    of equal steps ``Rx(a) Rz(g)``, so its y part is ``O(alpha gamma / n)``.
    """
    length = catheter.segment_length
    n = max(1, math.ceil(length / max_step - 1e-9))
    dl = length / n
    alpha, gamma = segment_bend_step(bend, dl, catheter.theta_max, length)
    points, r = advance_pose_steps(np.asarray(position, dtype=np.float64),
                                   np.asarray(rotation, dtype=np.float64), alpha, gamma, dl, n)
    return points[-1], r


@dataclass(frozen=True)
class PhantomConfig:
    """Physics settings of the simulated phantom."""

    catheter: CatheterConfig = field(default_factory=CatheterConfig)
    """The catheter model (segment length, diameter, theta_max, v_max)."""
    max_substep: float = 0.0005
    """Largest insertion per integration sub-step, m; [1e-5, 0.005]."""
    em_noise_rms: float = 0.0005
    """RMS (3-D) of the EM position noise, m (Aurora: ~0.5 mm); [0, 0.01]."""
    em_angle_noise_rms: float = 0.005
    """RMS of the EM orientation noise, rad; [0, 0.1]."""
    max_jump: float = 0.002
    """Slack of the re-homing test for delayed readings, m: a measured insertion change beyond
    ``catheter.max_insertion_speed * dt + max_jump`` is a re-referenced driver, not motion;
    [0, 0.1]."""
    wall_dt: float = 0.05
    """Step of the deformable wall (PBD + heartbeat), s; the physics steps it once this much
    time has accumulated; [1 ms, 0.2 s]."""
    fixture: str = 'none'
    """``'none'`` (the catheter in the aorta) or ``'bench'`` (clamped at the base of the
    steerable segment in free air: module docstring)."""

    def __post_init__(self) -> None:
        if not isinstance(self.catheter, CatheterConfig):
            raise ValueError(f"catheter must be a CatheterConfig, found "
                             f"{type(self.catheter).__name__}")
        for name, low, high, low_open in (
                ("max_substep", 1e-5, 0.005, False), ("em_noise_rms", 0.0, 0.01, False),
                ("em_angle_noise_rms", 0.0, 0.1, False), ("wall_dt", 1e-3, 0.2, False),
                ("max_jump", 0.0, 0.1, False)):
            value = getattr(self, name)
            ok = (isinstance(value, (int, float)) and math.isfinite(value)
                  and (value > low if low_open else value >= low) and value <= high)
            if not ok:
                raise ValueError(f"{name} must be in {'(' if low_open else '['}{low}, {high}], "
                                 f"found {value!r}")
        if self.fixture not in FIXTURES:
            raise ValueError(f"fixture must be one of {FIXTURES}, found {self.fixture!r}")


class PhantomPhysics:
    """Catheter-in-aorta physics (module docstring).

    Args:
        config: physics settings.
        wall: a :class:`~cgail_sim.wall.StaticWall` or ``DeformableWall`` (or None: no
            wall, free space).
    """

    def __init__(self, config: PhantomConfig, wall: Any | None = None,
                 plant: Plant | None = None) -> None:
        self.config = config
        self.wall = wall
        #: The true plant's insertion and tip compliance (None: a kinematic catheter that
        #: advances exactly as the given position).
        self.plant = plant
        self.radius = config.catheter.radius
        self.catheter = CatheterBatch(1, config.catheter, capacity=4096,
                                      max_step=config.max_substep)
        self.time = 0.0
        self.contacts = 0
        self.insertion_jumps = 0
        self.inserted = 0.0
        self._last_insertion: float | None = None
        self._wall_pending = 0.0
        #: Axial load of the last wall contact on the tip, N (0 without contact or plant).
        self.load = 0.0
        #: The tip's advance (insertion along the body, m) of the last step.
        self.last_advance = 0.0
        #: Bench fixture: the clamped base pose and the tip pose of the current bend.
        self._base: tuple[FloatArray, FloatArray] | None = None
        self._bench: tuple[FloatArray, FloatArray] | None = None

    def reset(self, position: FloatArray, rotation: FloatArray,
              introducer: FloatArray) -> None:
        """Put the tip at a start pose with its introducer behind it; wall at rest.

        Args:
            position: (3,) start position, m.
            rotation: (3, 3) start rotation.
            introducer: (3,) the proximal end of a straight introducer, or (K, 3) the nodes
                of a bent one (``StartConfig.introducer``,
                :func:`cgail_sim.ftl_model.seed_body`).
        """
        self.catheter.reset_env(0, np.asarray(position, dtype=np.float64),
                                np.asarray(rotation, dtype=np.float64),
                                np.asarray(introducer, dtype=np.float64))
        if self.wall is not None:
            self.wall.reset()
        self.time = 0.0
        self.contacts = 0
        self.inserted = 0.0
        self._last_insertion = None
        self._wall_pending = 0.0
        self.load = 0.0
        if self.plant is not None:
            self.plant.reset()
        if self.config.fixture == 'bench':
            self._base = (self.catheter.tip_position[0].copy(),
                          self.catheter.tip_rotation[0].copy())
            self._bench = bench_tip_pose(*self._base, (0.0, 0.0), self.config.catheter,
                                         self.config.max_substep)

    @property
    def tip_position(self) -> FloatArray:
        """(3,) true tip position, m."""
        if self._bench is not None:
            return self._bench[0].copy()
        return self.catheter.tip_position[0].copy()

    @property
    def tip_rotation(self) -> FloatArray:
        """(3, 3) true tip rotation."""
        if self._bench is not None:
            return self._bench[1].copy()
        return self.catheter.tip_rotation[0].copy()

    def step(self, dt: float, insertion_position: float | None,
             bend: tuple[float, float]) -> None:
        """Advance the physics by ``dt`` s.

        Args:
            dt: time step, s (> 0).
            insertion_position: the catheter's position at the driver's gripper, m (None: no
                reading yet; the first reading is the reference, no motion).
            bend: the segment's real ``(alpha, gamma)``, rad (the plant's bend).
        """
        if not (math.isfinite(dt) and dt > 0.0):
            raise ValueError(f"dt must be a positive number of seconds, found {dt!r}")
        self.time += dt
        self.last_advance = 0.0
        if self._base is not None:  # bench fixture: clamped, in free air
            self._bench = bench_tip_pose(*self._base, bend, self.config.catheter,
                                         self.config.max_substep)
            return
        if insertion_position is not None and math.isfinite(insertion_position):
            if self._last_insertion is None:
                self._last_insertion = insertion_position
            delta = insertion_position - self._last_insertion
            self._last_insertion = insertion_position
            cap = self.config.catheter.max_insertion_speed * dt + self.config.max_jump
            if abs(delta) > cap:
                # a re-homed or replaced driver: its position restarted, the catheter did not
                self.insertion_jumps += 1
            else:
                if self.plant is not None:
                    delta = self.plant.advance(delta, self.load)
                self.load = 0.0  # (set again by the contacts of this move)
                self.last_advance = delta
                self.move(delta, bend)
        if isinstance(self.wall, DeformableWall):
            self._wall_pending += dt
            if self._wall_pending >= self.config.wall_dt - 1e-12:
                body = self.catheter.body_points(0, 0.005)
                self.wall.step(self.time, self._wall_pending, body, self.radius)
                self._wall_pending = 0.0
                self._constrain()  # the wall moved (a rigid wall is checked after each move)

    def move(self, delta: float, bend: tuple[float, float]) -> None:
        """Insert (``delta > 0``) or retract the catheter by ``delta`` m with the given bend."""
        cfg = self.config
        cat = cfg.catheter
        remaining = float(delta)
        while abs(remaining) > 1e-12:
            dl = math.copysign(min(abs(remaining), cfg.max_substep), remaining)
            remaining -= dl
            alpha, gamma = segment_bend_step(bend, dl, self.catheter.theta_max,
                                             cat.segment_length)
            self.catheter.step(np.array([alpha]), np.array([gamma]), np.array([dl]))
            if dl > 0.0:
                self.inserted += dl
            self._constrain()

    def _constrain(self) -> None:
        if self.wall is None:
            return
        tip = self.catheter.tip_position[0]
        contact = self.wall.tip_contact(tip, self.radius, 0.01)
        if contact.penetration <= 0.0:
            return
        self.contacts += 1
        normal = np.asarray(contact.normal, dtype=np.float64)
        norm = math.sqrt(float(normal @ normal))  # = np.linalg.norm(normal)
        if norm < 1e-12:
            return
        normal = normal / norm
        i = int(self.catheter.tip_index[0])
        self.catheter.positions[0, i] = tip - contact.penetration * normal
        rot = self.catheter.rotations[0, i]
        heading = rot[:, 1]
        outward = float(heading @ normal)
        deflection = 0.0
        if self.plant is not None:
            self.load = max(self.load, self.plant.contact_load(contact.penetration,
                                                               contact.force))
            deflection = self.plant.tip_deflection(contact.penetration, contact.force)
        # the compliant tip leaves the wall at ``deflection`` inwards at least (0: it slides)
        if outward > -math.sin(deflection):
            tangent = heading - outward * normal
            n2 = math.sqrt(float(tangent @ tangent))  # = np.linalg.norm(tangent)
            if n2 > 1e-9:
                new_heading = (math.cos(deflection) * tangent / n2
                               - math.sin(deflection) * normal)
                self.catheter.rotations[0, i] = rotate_onto(heading, new_heading) @ rot

    def measured_pose(self, rng: np.random.Generator) -> tuple[FloatArray, FloatArray]:
        """The tip pose as the EM tracker sees it: position and small-angle orientation noise."""
        cfg = self.config
        p = self.tip_position + rng.normal(0.0, cfg.em_noise_rms / math.sqrt(3.0), 3)
        ang = rng.normal(0.0, cfg.em_angle_noise_rms / math.sqrt(2.0), 2)
        r = self.tip_rotation @ bend_rotation(np.array(ang[0]), np.array(ang[1]))
        return p, r

