"""Simulation environments for the insertion tasks: reset, 1 kHz torque steps, task-space state.

``InsertionEnv(task)`` covers all tasks (``gear``, ``peg``, ``block``, ``free``). Each ``step``
runs MuJoCo's ``mj_step2`` (integrate with the given torques) followed by ``mj_step1`` (positions,
velocities, contacts and bias forces of the *new* state), which costs one ``mj_step`` but leaves
every derived quantity (TCP pose, Jacobian, ``qfrc_bias``, contacts) consistent with ``q, dq``,
as a robot's sensors would be. ``contact_force`` is the force MuJoCo applied on the held part
during the last step.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import NamedTuple

import mujoco
import numpy as np
from numba import njit

from nf_core.friction import FrictionRanges
from nf_core.task_spec import TaskDraw
from sim_bridge_node.scenes import BLOCK_START_STD, CONTACT_FORCE_SENSOR, Scene, build_scene

ARM_START_STD = 0.2  # rad, per joint (the paper's simulated peg-in-hole start distribution)
START_CLEARANCE = 0.01  # m, sampled starts keep the TCP at least this far above the fixture mouth
MAX_START_TRIES = 1000


class Observation(NamedTuple):
    """State after a reset or a step (copies)."""

    q: np.ndarray
    dq: np.ndarray
    x: np.ndarray
    xdot: np.ndarray
    time: float


@njit(cache=True)
def _clamp_finite(tau: np.ndarray, lo: np.ndarray, hi: np.ndarray, out: np.ndarray) -> bool:
    """out = np.clip(tau, lo, hi) if every value is finite (True); else False and out untouched."""
    for i in range(tau.shape[0]):
        if not np.isfinite(tau[i]):
            return False
    for i in range(tau.shape[0]):
        out[i] = min(max(tau[i], lo[i]), hi[i])
    return True


@njit(cache=True)
def copy_if_finite(values: np.ndarray, out: np.ndarray) -> bool:
    """out[:] = values if every value is finite (True); else False and out untouched."""
    for i in range(values.shape[0]):
        if not np.isfinite(values[i]):
            return False
    for i in range(values.shape[0]):
        out[i] = values[i]
    return True


def joint_values(value: object, names: Sequence[str], what: str) -> np.ndarray:
    """A per-joint parameter (``joint_friction``, ``joint_viscous``) as an array of ``len(names)``
    finite values >= 0: a number, or a list of one value (for every joint) or one per joint.
    ``ValueError`` naming ``what`` and the joints otherwise."""
    n = len(names)
    items = [value] if isinstance(value, (str, bytes)) or not isinstance(value, Iterable) else list(value)
    if any(isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating))
           for v in items):
        raise ValueError(f"{what} must be a number or a list of numbers (one, or one per joint: "
                         f"{', '.join(names)}), got {value!r}")
    if len(items) not in (1, n):
        raise ValueError(f"{what} must have 1 value (every joint) or {n} (one per joint: {', '.join(names)}), "
                         f"got {len(items)}: {items}")
    arr = np.broadcast_to(np.asarray(items, dtype=float), (n,)).copy()
    bad = [names[i] for i in np.flatnonzero(~(np.isfinite(arr) & (arr >= 0.0)))]
    if bad:
        raise ValueError(f"{what} must be finite and >= 0 for every joint, got {arr.tolist()} (bad: {bad})")
    return arr


class InsertionEnv:
    """One simulated world: the Panda holding a gear or peg (or the 2-D block) and its fixture.

    ``reset(seed)``: ``seed`` None or negative gives the fixed start ``q_mean``; otherwise a
    start is drawn from ``N(q_mean, start_std^2)`` with a ``numpy`` Generator seeded by ``seed``,
    redrawn until it is inside the joint limits, collision-free, above the fixture and (if the scene
    has one, gear_clamp) with the TCP inside the scene's ``start_region``. With
    ``set_friction_ranges`` on, every reset also sets the episode's joint friction, drawn from the
    seed (``nf_core.friction``; ``episode_friction``), before the start state is set.
    ``step(tau)``: one 1 ms physics step with the joint torques (forces for the block) ``tau``,
    clamped to the actuator limits. Malformed torques raise ``ValueError`` before anything changes.
    """

    def __init__(
        self,
        task: str = "gear",
        *,
        plane: str = "vertical",
        start_std: float | np.ndarray | None = None,
        scene: Scene | None = None,
    ):
        """Build the scene for ``task`` (or use ``scene``, e.g. shared by a batch) and reset."""
        self.scene = scene if scene is not None else build_scene(task, plane=plane)
        task = self.scene.task
        self.task = task
        self.model = self.scene.model
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._qadr = np.array([m.joint(n).qposadr[0] for n in self.scene.joint_names])
        self._vadr = np.array([m.joint(n).dofadr[0] for n in self.scene.joint_names])
        self._contiguous = bool(
            np.array_equal(self._qadr, np.arange(m.nq)) and np.array_equal(self._vadr, np.arange(m.nv))
        )
        self._act = np.array([m.actuator(n).id for n in self.scene.actuator_names])
        if not np.array_equal(self._act, np.arange(m.nu)):
            raise RuntimeError("actuators must be declared in joint order")
        self._ctrl_lo = m.actuator_ctrlrange[:, 0].copy()
        self._ctrl_hi = m.actuator_ctrlrange[:, 1].copy()
        self._q_lo = m.jnt_range[[m.joint(n).id for n in self.scene.joint_names], 0].copy()
        self._q_hi = m.jnt_range[[m.joint(n).id for n in self.scene.joint_names], 1].copy()
        self._site = m.site(self.scene.tcp_site).id
        self._held = m.body(self.scene.held_body).id
        self._held_geoms = np.flatnonzero(m.geom_bodyid == self._held)
        self._force_adr = m.sensor_adr[m.sensor(CONTACT_FORCE_SENSOR).id]
        default_std = BLOCK_START_STD if task == "block" else ARM_START_STD
        if self.scene.start_std is not None:  # a task with its own start spread (gear_clamp)
            default_std = self.scene.start_std
        std = default_std if start_std is None else start_std
        self.start_std = np.broadcast_to(np.asarray(std, dtype=float), (self.nq,)).copy()
        self._vel6 = np.zeros(6)
        self._base_damping = m.dof_damping[self._vadr].copy()  # the scene's own (panda_spec.JOINT_DAMPING)
        self.friction_ranges = FrictionRanges()  # off: a reset leaves the model alone
        self.episode_friction: tuple[np.ndarray, np.ndarray] | None = None  # (Coulomb, added viscous) drawn
        self._axis_xy, self._top = self.scene.insertion_axis_xy.copy(), self.scene.insertion_top  # this episode's
        spec = self.scene.spec
        self.randomise = spec.randomise if spec is not None and spec.randomise.enabled else None
        self.episode_task: TaskDraw | None = None  # the cell's variation drawn for this episode
        if self.randomise is not None:  # the nominal values the draws vary
            self._fixture = m.body(self.scene.fixture_body).id
            self._fixture_pos0 = m.body_pos[self._fixture].copy()
            self._contact_geoms = np.flatnonzero(m.geom_friction[:, 0] == spec.friction)
            self._held_mass0, self._held_inertia0 = m.body_mass[self._held].copy(), m.body_inertia[self._held].copy()
        self._ctrl = self.data.ctrl  # view into MjData, reused every step
        self.last_torque = np.zeros(m.nu)
        self.reset()

    # ------------------------------------------------------------------ sizes and limits
    @property
    def nq(self) -> int:
        """Number of controlled joints (7 for the arm, 2 for the block)."""
        return len(self._qadr)

    @property
    def nu(self) -> int:
        """Number of actuators (equal to ``nq``)."""
        return self.model.nu

    @property
    def torque_limits(self) -> np.ndarray:
        """Symmetric actuator limits (Nm for the arm, N for the block)."""
        return self._ctrl_hi.copy()

    @property
    def q_mean(self) -> np.ndarray:
        """Fixed start configuration and mean of the start distribution."""
        return self.scene.q_mean.copy()

    @property
    def q_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper joint limits."""
        return self._q_lo.copy(), self._q_hi.copy()

    # ------------------------------------------------------------------ joint friction
    def set_joint_friction(self, coulomb: object = 0.0, viscous: object = 0.0) -> None:
        """Joint friction of the controlled joints, for identification tests and randomization:
        ``coulomb`` (Nm; N for the block) becomes MuJoCo's ``dof_frictionloss`` (a constraint-based
        Coulomb friction, at most that much torque against the motion) and ``viscous`` (Nm s/rad)
        is added to the scene's own viscous damping (``panda_spec.JOINT_DAMPING``) in ``dof_damping``.
        Each is a number or a list of one value per joint (or a single value for all); 0 (the
        default) leaves the scene as built. Neither shows in ``last_torque`` (the applied command,
        what ``joint_states.effort`` reports): the friction is part of the physics.

        Raises ``ValueError`` naming the parameter for a value that is not a finite number >= 0 or
        a list of the wrong length; nothing is changed then. The model is changed in place, so a
        batch sharing one scene shares the friction too."""
        names = self.scene.joint_names
        fc = joint_values(coulomb, names, "joint_friction")
        fv = joint_values(viscous, names, "joint_viscous")
        self.model.dof_frictionloss[self._vadr] = fc
        self.model.dof_damping[self._vadr] = self._base_damping + fv

    def set_friction_ranges(self, ranges: FrictionRanges) -> None:
        """Joint friction randomized per episode: from the next reset on, each ``reset(seed)`` sets
        ``set_joint_friction(*ranges.draw(seed, nq))`` (replacing any fixed friction set before) and
        keeps the draw in ``episode_friction``. ``FrictionRanges()`` (both [0, 0]) turns it off: resets
        leave the model as it is then. The model is shared by a batch sharing one scene (``BatchedEnv``
        gives each environment its own copy when the ranges are on)."""
        self.friction_ranges = ranges
        if not ranges.enabled:
            self.episode_friction = None

    @property
    def joint_friction(self) -> tuple[np.ndarray, np.ndarray]:
        """(Coulomb ``dof_frictionloss``, total viscous ``dof_damping``) of the controlled joints now."""
        return self.model.dof_frictionloss[self._vadr].copy(), self.model.dof_damping[self._vadr].copy()

    # ------------------------------------------------------------------ reset and step
    def reset(self, seed: int | None = None, q: np.ndarray | None = None) -> Observation:
        """Start a new episode at ``q`` (if given), the fixed start, or a start drawn with ``seed``.
        With friction ranges on, the episode's friction is drawn from ``seed`` (None or < 0: the
        ranges' middles) and set before the start state; a refused start changes neither."""
        if self.randomise is not None:  # the cell first: the start is checked against this episode's fixture
            spec = self.scene.spec
            self._set_cell(self.randomise.draw(seed, spec.friction, spec.part.mass))
        if q is not None:
            q0 = self._checked_vector(q, self.nq, "start configuration")
            problem = self._start_problem(q0, require_above=False)
            if problem:
                raise ValueError(f"start configuration rejected: {problem}")
        elif seed is None or seed < 0:
            q0 = self.scene.q_mean.copy()
        else:
            q0 = self.sample_start(seed)
        if self.friction_ranges.enabled:  # friction leaves the start alone: it acts on motion only
            coulomb, viscous = self.friction_ranges.draw(seed, self.nq)
            self.set_joint_friction(coulomb, viscous)
            self.episode_friction = (coulomb, viscous)
        self._set_state(q0)
        return self.observation()

    def _set_cell(self, draw: TaskDraw) -> None:
        """Put this episode's variation of the cell into the model: the fixture moved, the contacts'
        friction, the part's mass and inertia. What the controller is given (the goal) stays nominal."""
        m, spec = self.model, self.scene.spec
        m.body_pos[self._fixture] = self._fixture_pos0 + draw.fixture_offset
        m.geom_friction[self._contact_geoms, 0] = draw.friction
        scale = draw.part_mass / spec.part.mass
        m.body_mass[self._held] = self._held_mass0 * scale
        m.body_inertia[self._held] = self._held_inertia0 * scale
        self._axis_xy = self.scene.insertion_axis_xy + draw.fixture_offset[:2]
        self._top = self.scene.insertion_top + float(draw.fixture_offset[2])
        self.episode_task = draw

    def sample_start(self, seed: int) -> np.ndarray:
        """The start configuration ``reset(seed)`` would use (deterministic per seed)."""
        rng = np.random.default_rng(seed)
        for _ in range(MAX_START_TRIES):
            q0 = self.scene.q_mean + self.start_std * rng.standard_normal(self.nq)
            if not self._start_problem(q0, require_above=True):
                return q0
        raise RuntimeError(f"no valid start found in {MAX_START_TRIES} draws (seed {seed})")

    def _start_problem(self, q0: np.ndarray, *, require_above: bool) -> str:
        """Why ``q0`` is not a valid start ("" if it is). Clobbers the simulation state."""
        if np.any(q0 <= self._q_lo) or np.any(q0 >= self._q_hi):
            bad = np.flatnonzero((q0 <= self._q_lo) | (q0 >= self._q_hi))
            return f"outside the joint limits at {[self.scene.joint_names[i] for i in bad]}"
        self._set_state(q0)
        if self.data.ncon:
            c = self.data.contact
            names = self.model.geom
            pairs = {(names(g1).name, names(g2).name) for g1, g2 in zip(c.geom1, c.geom2, strict=True)}
            return f"in collision: {sorted(pairs)}"
        if require_above and self.data.site_xpos[self._site, 2] < self._top + START_CLEARANCE:
            return "TCP not above the fixture"
        region = self.scene.start_region
        if require_above and region is not None:
            tcp = self.data.site_xpos[self._site]
            if np.any(tcp < region[0]) or np.any(tcp > region[1]):
                return "TCP outside the task's start region"
        return ""

    def _set_state(self, q0: np.ndarray) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._qadr] = q0
        self.last_torque[:] = 0.0
        mujoco.mj_forward(self.model, self.data)

    @staticmethod
    def _checked_vector(value: np.ndarray, size: int, what: str, finite: bool = True) -> np.ndarray:
        try:
            arr = np.asarray(value, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{what} must be a numeric array of {size} values: {exc}") from None
        if arr.shape != (size,):
            raise ValueError(f"{what} must have shape ({size},), got shape {arr.shape}")
        if finite and not np.isfinite(arr).all():
            bad = np.flatnonzero(~np.isfinite(arr)).tolist()
            raise ValueError(f"{what} contains NaN or Inf at index {bad}: {arr.tolist()}")
        return arr

    def step(self, tau: np.ndarray) -> None:
        """Advance 1 ms with torques ``tau`` (clamped to the limits). Raises ``ValueError`` on
        NaN/Inf or a wrong size, leaving the state untouched."""
        arr = self._checked_vector(tau, self.model.nu, "torque command", finite=False)
        if not self.step_if_finite(arr):  # the compiled pass checks finiteness once
            self._checked_vector(arr, self.model.nu, "torque command")  # raises, naming the bad entries

    def step_if_finite(self, tau: np.ndarray) -> bool:
        """``step`` for a float array of ``nu`` torques, checked and clamped in one compiled pass:
        False (no step, state untouched) when one is NaN or Inf."""
        if not _clamp_finite(tau, self._ctrl_lo, self._ctrl_hi, self.last_torque):
            return False
        self._step_clamped()
        return True

    def _step_clamped(self) -> None:
        """Physics step with ``last_torque`` already valid and clamped (the batch calls this)."""
        self._ctrl[:] = self.last_torque
        mujoco.mj_step2(self.model, self.data)
        mujoco.mj_step1(self.model, self.data)

    def observation(self) -> Observation:
        """Joint and task-space state now."""
        return Observation(self.q, self.dq, self.x, self.xdot, self.time)

    # ------------------------------------------------------------------ state
    @property
    def q(self) -> np.ndarray:
        """Joint positions (rad; m for the block)."""
        return self.data.qpos[: self.nq].copy() if self._contiguous else self.data.qpos[self._qadr]

    @property
    def dq(self) -> np.ndarray:
        """Joint velocities."""
        return self.data.qvel[: self.nq].copy() if self._contiguous else self.data.qvel[self._vadr]

    def state_views(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(q, dq) as views into the simulator's state, which every step and reset rewrite in place
        (None when the joints are not contiguous): for a caller that reads them before the next step
        and keeps no reference, without the copies of ``q`` and ``dq``."""
        if not self._contiguous:
            return None
        return self.data.qpos[: self.nq], self.data.qvel[: self.nq]

    @property
    def x(self) -> np.ndarray:
        """TCP position in the world frame (m)."""
        return self.data.site_xpos[self._site].copy()

    @property
    def tcp_rotation(self) -> np.ndarray:
        """TCP orientation (3x3, columns = hand axes in the world frame)."""
        return self.data.site_xmat[self._site].reshape(3, 3).copy()

    @property
    def xdot(self) -> np.ndarray:
        """TCP linear velocity in the world frame (m/s)."""
        mujoco.mj_objectVelocity(self.model, self.data, mujoco.mjtObj.mjOBJ_SITE, self._site, self._vel6, 0)
        return self._vel6[3:].copy()

    def tcp_jacobian(self) -> np.ndarray:
        """6 x nv Jacobian of the TCP site, rows: linear velocity, then angular velocity (world)."""
        jac = np.zeros((6, self.model.nv))
        mujoco.mj_jacSite(self.model, self.data, jac[:3], jac[3:], self._site)
        return jac

    @property
    def bias_torques(self) -> np.ndarray:
        """Gravity, Coriolis and centrifugal joint torques at the current state (``qfrc_bias``)."""
        return self.data.qfrc_bias[self._vadr].copy()

    @property
    def time(self) -> float:
        """Simulated time since reset (s)."""
        return float(self.data.time)

    # ------------------------------------------------------------------ task
    @property
    def goal_position(self) -> np.ndarray:
        """TCP position at full insertion (world frame): the controller's ``x_ref``."""
        return self.scene.goal_position.copy()

    @property
    def insertion_depth(self) -> float:
        """How far the TCP is below the fixture mouth while inside the opening (m, >= 0)."""
        tcp = self.data.site_xpos[self._site]
        lateral = np.abs(tcp[:2] - self._axis_xy)
        inside = np.hypot(*lateral) < self.scene.lateral_tolerance
        if self.scene.kind == "peg":
            inside = bool(np.max(lateral) < self.scene.lateral_tolerance)
        elif self.task == "block":
            inside = bool(lateral[0] < self.scene.lateral_tolerance)
        depth = self._top - tcp[2]
        return float(max(depth, 0.0)) if inside else 0.0

    @property
    def success(self) -> bool:
        """Inserted at least the task's success depth (16 mm gear/peg, 25 mm block)."""
        return self.task != "free" and self.insertion_depth >= self.scene.success_depth

    @property
    def contact_force(self) -> np.ndarray:
        """Net contact force on the held part (gear, peg or block) during the last step (N, world)."""
        adr = self._force_adr
        return -self.data.sensordata[adr : adr + 3].copy()

    @property
    def penetration(self) -> float:
        """Deepest interpenetration of the held part with anything, now (m, >= 0)."""
        n = self.data.ncon
        if n == 0:
            return 0.0
        c = self.data.contact
        mine = np.isin(c.geom1, self._held_geoms) | np.isin(c.geom2, self._held_geoms)
        if not np.any(mine):
            return 0.0
        return float(max(0.0, -np.min(c.dist[mine])))
