"""Per-joint friction of an arm identified from a recorded bag: a Coulomb and a viscous term per
joint, from the joint states alone (position, velocity and effort over time). ROS-free.

    python -m nf_bags.friction BAG [--json out.json] [--min-speed 0.05] [--model auto|panda|fr3]
        [--urdf FILE] [--held-part auto|gear|peg|none] [--effort auto|applied|no-gravity] [--arm /arm0]

Method, per recorded joint state (``/joint_states``, or an arm's ``/armN/joint_states``):

1. Segments: the states are cut at gaps (a stamp step over ``GAP_FACTOR`` times the median),
   reset states (all velocities and efforts exactly 0, as the sim publishes them) and position jumps
   the velocities do not explain; each segment is smoothed on its own.
2. Smoothing and acceleration: a Savitzky-Golay fit (a quadratic in time over ``window`` s, with the
   true sample times, so a driver's 100 Hz timer jitter is no error) smooths the velocity and the
   effort alike; the acceleration is the derivative of the smoothed velocity (three-point formula),
   so acceleration and effort pass the same filter (the fit's own slope has another frequency
   response than its value, which biases the viscous terms). Samples whose window leaves the
   segment are dropped. The acceleration is taken half a torque period later and the effort
   ``EFFORT_DELAY`` later (see there).
3. Model torque: ``pinocchio.rnea(q, dq, ddq)`` = M(q) ddq + C(q, dq) dq + g(q) of the
   controller's own arm model (``nf_controller_node.arm_model.ArmModel``: the description, the held
   part, the rotor armature). Which part of it the effort holds depends on the driver:

   - ``applied``: the torque the joint motors apply, gravity included. The MuJoCo sim's
     ``joint_states`` (``sim_bridge``; with ``driver_gravity_compensation`` it reports the command's
     part, ``no-gravity``, and says so in its diagnostics' ``effort`` value). Its joint friction is
     physics, not part of the effort, so it shows as the residual.
   - ``no-gravity``: the command on top of the robot's own gravity compensation. The Franka
     driver's ``joint_states`` (``franka_driver``: the torque written to libfranka, which adds
     g(q) itself; libfranka's ``Torques`` are "desired torques without gravity and friction",
     so on a real arm the friction the robot compensates itself is not in the residual, only
     what its compensation leaves). The model torque is then M ddq + C dq.

   ``auto`` reads the bag's ``/diagnostics`` (a driver status's ``effort`` value, else its name:
   ``sim_bridge: driver`` or ``franka_driver: robot``);
   without them the data decides (whichever leaves the smaller residual; gravity is tens of Nm on
   the shoulder and elbow, friction a few). Either way both residuals are reported, and a choice
   the data contradicts is warned about.
4. Fit, per joint, over the samples moving faster than ``min_speed`` (rad/s): the residual
   ``r = effort - model torque`` by least squares as

       r = coulomb * sign(dq) + viscous * dq + offset

   Friction opposes motion: the friction torque on the joint is -(coulomb sign(dq) + viscous dq),
   which the motors supply on top of the rigid-body torque, so dissipative friction gives
   coulomb >= 0 and viscous >= 0 (the MuJoCo ``frictionloss`` and ``damping`` of a joint). The
   offset takes what is not friction and does not change sign with the motion (a gravity model
   error, a constant load). The fit is repeated without the samples more than ``OUTLIER`` robust
   standard deviations off it (an impact, a torque kink the smoothing smears, MuJoCo's soft
   friction near zero speed); they are counted. Negative terms are warned about (friction does
   not push), and so is a recorded contact of the held part. A joint that did not move faster than ``min_speed`` for
   ``min_samples`` samples each way, or only at one speed (Coulomb and viscous cannot be told
   apart), is reported as not identified, with the reason, never with a number.

Contact with the world, a held part missing from the model or a model error also land in the
residual: identify from free-space motion that moves every joint both ways at several speeds.

Exit codes: 0 every joint identified, 1 some joints not identified (warned), 2 no joint states in
the bag, an unreadable bag or bad options.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .bagfile import BagError, scan
from .reader import policies, read_messages, stamp_ns
from .topics import JOINT_STATES, TASK_STATUS, arm_of, arm_topic

EFFORTS = ("auto", "applied", "no-gravity")
MODELS = ("auto", "panda", "fr3")
HELD_PARTS = ("auto", "gear", "peg", "none")
DIAGNOSTICS = "/diagnostics"
DRIVER_STATUS = {"sim_bridge: driver": "applied", "franka_driver: robot": "no-gravity"}  # diagnostics name -> effort
GAP_FACTOR = 3.0  # a stamp step over this many times the median step starts a new segment
JUMP = 0.02  # rad: a position step this much off what the velocities explain starts a new segment
MIN_WINDOW = 5  # samples in the smoothing window at least (a quadratic needs 3; 5 to smooth)
MAX_CONDITION = 100.0  # of the normalized [sign(dq), dq, 1] regressors: above, Coulomb and viscous are not separable
# Timing. Both drivers hold each torque for one 1 kHz period: the acceleration it causes is the period's
# mean, half a period after the state it was applied at. And the effort stamped t was applied at the state
# of t - delay: the sim's effort is the torque of the physics step that ended at t (applied 1 ms earlier),
# the Franka driver's the command computed from the state stamped t. Getting either wrong biases the viscous
# terms (an effort delay off by a step: by about gravity's slope times the step, on the shoulder).
TORQUE_PERIOD = 0.001  # s
EFFORT_DELAY = {"applied": 0.001, "no-gravity": 0.0}  # s, of each convention's usual driver
DRIVER_DELAY = {"sim_bridge: driver": 0.001, "franka_driver: robot": 0.0}  # s, by the driver's status name
OUTLIER = 5.0  # robust standard deviations: a sample's residual further from the fit is left out
OUTLIER_FLOOR = 0.005  # Nm: the robust standard deviation taken as at least this (noise-free simulations)
OUTLIER_ROUNDS = 3  # refits without the outliers at most
NEGATIVE = 0.01  # Nm, Nm s/rad: a fitted term below minus this is warned about (friction does not push)
CONTACT = 1.0  # N: a recorded contact force above this is warned about
CHUNK = 20_000  # samples smoothed per batch (memory)


class NoJointStatesError(ValueError):
    """The bag holds no usable joint states (no topic, no effort, or nothing that moved)."""


# ---------------------------------------------------------------------- reading
@dataclass
class JointStates:
    """Recorded joint states by stamp, each stamp once (lockstep resends dropped), in stamp order."""

    topic: str
    names: list[str]
    t: np.ndarray  # (n,) s since the first state
    q: np.ndarray  # (n, nq) rad
    dq: np.ndarray  # (n, nq) rad/s
    effort: np.ndarray  # (n, nq) Nm


def joint_state_topic(bag: str | Path, arm: str | None = None) -> str:
    """The joint states topic of ``arm`` ("/", "/arm0"), or of the bag's only arm with joint states."""
    counts = scan(bag).counts
    found = sorted(t for t, c in counts.items() if c and t.endswith(JOINT_STATES) and arm_of(t) is not None)
    if arm is not None:
        topic = arm_topic(arm, JOINT_STATES)
        if topic not in found:
            raise NoJointStatesError(f"{bag} has no {topic} messages (joint states: {found or 'none'})")
        return topic
    if not found:
        raise NoJointStatesError(f"{bag} has no joint states (no {JOINT_STATES} messages; topics: "
                                 f"{sorted(counts) or 'none'}): record the driver's {JOINT_STATES} "
                                 f"(python -m nf_bags.record --topics {JOINT_STATES} ...)")
    if len(found) > 1:
        raise NoJointStatesError(f"{bag} holds the joint states of several arms ({found}): choose one with --arm")
    return found[0]


def load_joint_states(bag: str | Path, topic: str = JOINT_STATES) -> JointStates:
    """The joint states of ``topic``; ``NoJointStatesError`` if they carry no effort or change joints."""
    rows: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    names: list[str] = []
    for d in read_messages(bag, [topic]):
        m = d.msg
        got = list(m.name)
        if not names:
            names = got
            if len(set(names)) != len(names):
                raise NoJointStatesError(f"{topic}: duplicate joint names {names}")
        order = list(range(len(names)))
        if got != names:
            if sorted(got) != sorted(names):
                raise NoJointStatesError(f"{topic}: the joints change from {names} to {got}")
            order = [got.index(n) for n in names]
        if not (len(m.position) == len(m.velocity) == len(m.effort) == len(got)):
            raise NoJointStatesError(f"{topic}: a state with {len(got)} names, {len(m.position)} positions, "
                                     f"{len(m.velocity)} velocities and {len(m.effort)} efforts: identification "
                                     f"needs all three for every joint")
        stamp = stamp_ns(m.header)
        if stamp not in rows:
            q, dq, tau = (np.asarray(x, dtype=np.float64)[order] for x in (m.position, m.velocity, m.effort))
            rows[stamp] = (q, dq, tau)
    if not rows:
        raise NoJointStatesError(f"{bag} has no {topic} messages")
    stamps = np.array(sorted(rows), dtype=np.int64)
    n = len(names)

    def col(i: int) -> np.ndarray:
        return np.array([rows[s][i] for s in stamps], dtype=np.float64).reshape(len(stamps), n)

    return JointStates(topic, names, (stamps - stamps[0]) * 1e-9, col(0), col(1), col(2))


def recorded_drivers(bag: str | Path, limit: int = 50) -> dict[str, str]:
    """The effort conventions of the drivers whose status is in the bag's first ``limit``
    ``/diagnostics`` messages (a status's ``effort`` value, else ``DRIVER_STATUS`` of its name), each
    with the status's name."""
    if not scan(bag).counts.get(DIAGNOSTICS):
        return {}
    found: dict[str, str] = {}
    for i, d in enumerate(read_messages(bag, [DIAGNOSTICS])):
        for s in d.msg.status:
            said = next((kv.value for kv in s.values if kv.key == "effort" and kv.value in EFFORTS[1:]), None)
            if said or s.name in DRIVER_STATUS:
                found.setdefault(said or DRIVER_STATUS[s.name], s.name)
        if i + 1 >= limit:
            break
    return found


def recorded_task_of(bag: str | Path, topic: str) -> tuple[str | None, float]:
    """The task the arm of joint states ``topic`` reported on its task status (None without one) and
    the largest contact force on its held part (N) the task status reported."""
    task, force = None, 0.0
    for d in read_messages(bag, [arm_topic(arm_of(topic) or "/", TASK_STATUS)]):
        task = task or str(d.msg.task)
        force = max(force, float(d.msg.contact_force))
    return task, force


# ---------------------------------------------------------------------- smoothing
def segment_ids(t: np.ndarray, q: np.ndarray, dq: np.ndarray, effort: np.ndarray) -> np.ndarray:
    """A segment number per sample (-1: a reset state, used by none): a new segment starts after a
    gap in the stamps, a reset state, or a position jump the velocities do not explain."""
    n = len(t)
    reset = np.all(dq == 0.0, axis=1) & np.all(effort == 0.0, axis=1)
    if n < 2:
        return np.where(reset, -1, 0)
    step = np.diff(t)
    median = float(np.median(step[step > 0])) if np.any(step > 0) else 0.0
    explained = 0.5 * (dq[1:] + dq[:-1]) * step[:, None]
    jump = np.max(np.abs(np.diff(q, axis=0) - explained), axis=1) > JUMP
    cut = (step <= 0.0) | (step > GAP_FACTOR * median) | jump | reset[1:] | reset[:-1]
    seg = np.concatenate([[0], np.cumsum(cut)])
    return np.where(reset, -1, seg)


def savgol(t: np.ndarray, y: np.ndarray, seg: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Savitzky-Golay with the true sample times: per sample k, the least-squares quadratic
    ``y(t_k + s) = c0 + c1 s + c2 s^2`` over the ``2 half + 1`` samples around it. Returns (valid,
    coefficients (n, 3, m) for ``y`` (n, m)): valid where the window stays in one segment (else NaN)."""
    n, m = y.shape
    coef = np.full((n, 3, m), np.nan)
    valid = np.zeros(n, dtype=bool)
    if n < 2 * half + 1:
        return valid, coef
    centre = np.arange(half, n - half)
    ok = (seg[centre - half] == seg[centre + half]) & (seg[centre] >= 0)
    centre = centre[ok]
    offsets = np.arange(-half, half + 1)
    for start in range(0, len(centre), CHUNK):
        k = centre[start : start + CHUNK]
        idx = k[:, None] + offsets[None, :]
        T = t[idx] - t[k][:, None]  # (c, w) s
        scale = np.max(np.abs(T), axis=1, keepdims=True)  # to [-1, 1]: a well-conditioned fit
        s = T / scale
        A = np.stack([np.ones_like(s), s, s * s], axis=2)  # (c, w, 3)
        c = np.linalg.solve(A.transpose(0, 2, 1) @ A, A.transpose(0, 2, 1) @ y[idx])  # (c, 3, m), scaled time
        coef[k] = c / np.stack([np.ones_like(scale), scale, scale * scale], axis=1)
        valid[k] = True
    return valid, coef


def smoothed_slope(t: np.ndarray, y: np.ndarray, valid: np.ndarray, seg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The derivative of the smoothed ``y`` (n, m) by the three-point formula on the true sample times
    (exact for a quadratic); valid where the sample and both neighbours are valid and in one segment."""
    n = len(t)
    out = np.full_like(y, np.nan)
    ok = np.zeros(n, dtype=bool)
    if n < 3:
        return ok, out
    k = np.arange(1, n - 1)
    ok[k] = valid[k - 1] & valid[k] & valid[k + 1] & (seg[k - 1] == seg[k + 1])
    k = k[ok[k]]
    h1 = (t[k] - t[k - 1])[:, None]
    h2 = (t[k + 1] - t[k])[:, None]
    out[k] = (-h2 / (h1 * (h1 + h2)) * y[k - 1] + (h2 - h1) / (h1 * h2) * y[k] + h1 / (h2 * (h1 + h2)) * y[k + 1])
    return ok, out


# ---------------------------------------------------------------------- model
def _task_part(task: str) -> str:
    """The held part of a recorded task (``Part.text``): its task file's, or the gear when the file is not here."""
    from nf_core.task_spec import TaskFileError, load_task

    try:
        return load_task(task).part.text()
    except TaskFileError:
        return "gear"


def arm_model(kind: str, names: Sequence[str], urdf: str | None, held_part: str, armature: np.ndarray | None
              ) -> tuple[Any, str]:
    """The controller's Pinocchio ``ArmModel`` of arm ``kind`` (auto: from the joint names) holding
    ``held_part``, with ``urdf`` instead of the arm's description if given; and its kind."""
    from franka_driver.robot_model import SPECS
    from nf_controller_node.arm_model import ArmModel
    from nf_core.task_spec import held_part_inertia

    if kind == "auto":
        kinds = [k for k, spec in SPECS.items() if sorted(names) == sorted(spec.joint_names)]
        if not kinds:
            raise ValueError(f"joints {list(names)} are neither the Panda's (panda_joint1..7) nor the FR3's "
                             f"(fr3_joint1..7): give --model panda|fr3 (and --urdf) for another naming")
        kind = kinds[0]
    spec = SPECS[kind]
    if sorted(names) != sorted(spec.joint_names):
        raise ValueError(f"the recorded joints {list(names)} are not the {kind}'s {list(spec.joint_names)}")
    model = ArmModel(urdf or spec.urdf_path(), armature=armature, part=held_part_inertia(held_part),
                     joint_names=spec.joint_names, finger_joint_names=spec.finger_joint_names,
                     hand_frame=spec.hand_frame)
    return model, kind


def model_torques(model: Any, q: np.ndarray, dq: np.ndarray, ddq: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M ddq + C dq + g, g) per sample (Nm), with Pinocchio's RNEA (armature included)."""
    import pinocchio as pin

    data = model.createData()
    tau = np.empty_like(q)
    g = np.empty_like(q)
    for i in range(len(q)):
        tau[i] = pin.rnea(model, data, q[i], dq[i], ddq[i])
        g[i] = pin.computeGeneralizedGravity(model, data, q[i])
    return tau, g


# ---------------------------------------------------------------------- fit
@dataclass
class JointFriction:
    """The friction identified for one joint (NaN and a ``reason`` when it was not identified)."""

    name: str
    coulomb: float  # Nm, >= 0 when friction opposes motion
    viscous: float  # Nm s/rad
    offset: float  # Nm, the part of the residual that does not change sign with the motion
    samples: int  # used in the fit (|dq| > min_speed, outliers left out)
    samples_positive: int  # of those, moving in + and - direction
    samples_negative: int
    outliers: int  # samples left out: residual over OUTLIER robust sigmas from the fit (an impact, a kink)
    rms: float  # Nm, residual RMS after the fit
    r2: float  # share of the residual's variance the fit explains
    identified: bool
    reason: str = ""


def fit_joint(name: str, r: np.ndarray, dq: np.ndarray, min_speed: float, min_samples: int) -> JointFriction:
    """Least squares ``r = coulomb sign(dq) + viscous dq + offset`` over the samples with |dq| > min_speed,
    refitted without the samples more than ``OUTLIER`` robust standard deviations off (at most
    ``OUTLIER_ROUNDS`` times)."""
    moving = np.abs(dq) > min_speed
    y, v = r[moving], dq[moving]
    X = np.column_stack([np.sign(v), v, np.ones_like(v)])
    keep = np.ones(len(v), dtype=bool)
    nan = float("nan")
    for _ in range(OUTLIER_ROUNDS + 1):
        pos, neg = int(np.sum(v[keep] > 0)), int(np.sum(v[keep] < 0))
        if min(pos, neg) < min_samples:
            return JointFriction(name, nan, nan, nan, pos + neg, pos, neg, int((~keep).sum()), nan, nan, False,
                                 f"moved faster than {min_speed:g} rad/s in {pos} samples one way and {neg} the "
                                 f"other (needs {min_samples} each way)")
        Xk = X[keep]
        if np.linalg.cond(Xk / np.linalg.norm(Xk, axis=0)) > MAX_CONDITION:
            speeds = np.abs(v[keep])
            return JointFriction(name, nan, nan, nan, pos + neg, pos, neg, int((~keep).sum()), nan, nan, False,
                                 f"moved at too uniform a speed ({speeds.min():.3g}-{speeds.max():.3g} rad/s) to "
                                 f"tell Coulomb from viscous friction")
        coef, *_ = np.linalg.lstsq(Xk, y[keep], rcond=None)
        res = y - X @ coef
        sigma = 1.4826 * float(np.median(np.abs(res[keep] - np.median(res[keep]))))  # robust standard deviation
        within = np.abs(res) <= OUTLIER * max(sigma, OUTLIER_FLOOR)
        if np.array_equal(within, keep):
            break
        keep = within
    yk, rk = y[keep], res[keep]
    total = float(np.sum((yk - yk.mean()) ** 2))
    r2 = 1.0 - float(np.sum(rk**2)) / total if total > 0.0 else nan
    return JointFriction(name, float(coef[0]), float(coef[1]), float(coef[2]), pos + neg, pos, neg,
                         int((~keep).sum()), float(np.sqrt(np.mean(rk**2))), r2, True)


@dataclass
class Fit:
    """The fit of every joint, with the effort convention it used and the smoothing facts."""

    effort: str  # applied | no-gravity
    effort_source: str  # why that convention
    effort_delay: float  # s: the effort stamped t taken as the torque at t - effort_delay
    residual_rms: dict[str, float]  # convention -> RMS of the residual over the moving samples (all joints)
    joints: list[JointFriction]
    states: int
    rate_hz: float  # median
    segments: int
    samples: int  # smoothed samples (a full window inside a segment)
    window: float  # s, the smoothing window used


def identify(states: JointStates, model: Any, effort: str = "auto", drivers: Mapping[str, str] | None = None,
             min_speed: float = 0.05, window: float = 0.02, min_samples: int = 50,
             effort_delay: float | None = None) -> Fit:
    """The fit of every joint of ``states`` against ``model`` (an ``ArmModel``; joints matched by
    name); ``drivers``: the effort conventions the bag's diagnostics name (``recorded_drivers``);
    ``effort_delay``: s the effort lags its stamp (None: ``DRIVER_DELAY`` of the one driver the
    diagnostics name, else ``EFFORT_DELAY`` of the convention)."""
    if effort not in EFFORTS:
        raise ValueError(f"effort must be one of {EFFORTS}, got {effort!r}")
    if effort_delay is not None and not abs(effort_delay) <= 0.1:
        raise ValueError(f"effort delay must be within +-0.1 s, got {effort_delay}")
    if not (min_speed > 0.0 and window > 0.0 and min_samples >= 3):
        raise ValueError(f"need min_speed > 0, window > 0 and min_samples >= 3, got {min_speed}, {window}, "
                         f"{min_samples}")
    order = [states.names.index(n) for n in model.joint_names]
    t = states.t
    q, dq, tau = states.q[:, order], states.dq[:, order], states.effort[:, order]
    seg = segment_ids(t, q, dq, tau)
    step = np.diff(t)
    dt = float(np.median(step[step > 0])) if np.any(step > 0) else 0.0
    half = max((MIN_WINDOW - 1) // 2, round(0.5 * window / dt) if dt > 0 else 0)
    nq = q.shape[1]
    valid, coef = savgol(t, np.hstack([dq, tau]), seg, half)
    dq_s = coef[:, 0, :nq]
    # the acceleration from the smoothed velocity, so it and the effort pass the same filter; taken half a
    # torque period later: the mean over the period the torque was held
    valid, ddq = smoothed_slope(t, dq_s, valid, seg)
    ddq += coef[:, 2, :nq] * TORQUE_PERIOD
    moving = valid & np.any(np.abs(dq_s) > min_speed, axis=1)
    segments = len(set(seg[seg >= 0].tolist()))
    if not moving.any():
        raise NoJointStatesError(f"{states.topic}: no joint moved faster than {min_speed:g} rad/s over a full "
                                 f"smoothing window ({len(t)} states, {segments} segment(s))")
    rigid, g = model_torques(model.model, q[moving], dq_s[moving], ddq[moving])
    if effort_delay is None and drivers is not None and len(drivers) == 1:
        effort_delay = DRIVER_DELAY.get(next(iter(drivers.values())))  # the named driver's, either convention
    delays = {k: EFFORT_DELAY[k] if effort_delay is None else effort_delay for k in EFFORT_DELAY}
    c = coef[moving][:, :, nq:]  # the effort's quadratic around each state
    # the effort stamped t was applied from the state at t - delay: the state at t got the effort at t + delay
    residual = {k: c[:, 0] + c[:, 1] * delays[k] + c[:, 2] * delays[k] ** 2 - rigid + (g if k == "no-gravity" else 0.0)
                for k in EFFORT_DELAY}
    rms = {k: float(np.sqrt(np.mean(v**2))) for k, v in residual.items()}
    by_data, other = sorted(rms, key=rms.__getitem__)
    if effort != "auto":
        chosen, why = effort, "given (--effort)"
    elif drivers is not None and len(drivers) == 1:
        chosen = next(iter(drivers))
        why = f"the bag's /diagnostics name the driver ({drivers[chosen]!r})"
    else:
        chosen = by_data
        why = (f"the data: residual RMS {rms[by_data]:.3g} Nm as {by_data!r} vs {rms[other]:.3g} Nm as {other!r}; "
               + ("the /diagnostics name drivers of both kinds" if drivers else "no driver status in /diagnostics"))
    r, dq_m = residual[chosen], dq_s[moving]
    joints = [fit_joint(n, r[:, i], dq_m[:, i], min_speed, min_samples) for i, n in enumerate(model.joint_names)]
    return Fit(chosen, why, delays[chosen], rms, joints, len(t), 1.0 / dt if dt > 0 else float("nan"), segments,
               int(valid.sum()), 2 * half * dt)


@dataclass
class FrictionResult:
    """What ``identify_bag`` found, with what it assumed."""

    bag: str
    topic: str
    model: str  # panda | fr3
    urdf: str
    held_part: str
    held_part_source: str
    armature: list[float]  # kg m^2
    min_speed: float  # rad/s
    fit: Fit
    warnings: list[str] = field(default_factory=list)

    @property
    def joints(self) -> list[JointFriction]:
        """Per joint, in the model's order."""
        return self.fit.joints

    @property
    def identified(self) -> bool:
        """Every joint identified."""
        return all(j.identified for j in self.joints)

    def sim_parameters(self) -> dict[str, list[float]]:
        """The MuJoCo sim's parameters that give its Panda this friction: ``joint_friction`` (Coulomb,
        Nm) and ``joint_viscous`` (Nm s/rad, on top of the arm's own ``panda_spec.JOINT_DAMPING``,
        which the sim always has); joints not identified and negative values give 0."""
        from nf_core.panda_spec import JOINT_DAMPING

        def clean(values: Sequence[float]) -> list[float]:
            return [round(max(0.0, v), 4) if np.isfinite(v) else 0.0 for v in values]

        return {"joint_friction": clean([j.coulomb for j in self.joints]),
                "joint_viscous": clean([j.viscous - JOINT_DAMPING[i] for i, j in enumerate(self.joints)])}

    def as_dict(self) -> dict[str, Any]:
        """Plain data for ``--json`` (NaN as null)."""
        out = asdict(self)
        out["identified"] = self.identified
        out["sim_parameters"] = self.sim_parameters()
        for j in out["fit"]["joints"]:
            for k, v in j.items():
                if isinstance(v, float) and not np.isfinite(v):
                    j[k] = None
        return out


def identify_bag(bag: str | Path, *, arm: str | None = None, model: str = "auto", urdf: str | None = None,
                 held_part: str = "auto", armature: Sequence[float] | None = None, effort: str = "auto",
                 min_speed: float = 0.05, window: float = 0.02, min_samples: int = 50,
                 effort_delay: float | None = None) -> FrictionResult:
    """Read ``bag`` and identify the friction of every joint of its (only, or ``arm``'s) joint states."""
    from franka_driver.robot_model import SPECS
    from nf_core.panda_spec import JOINT_ARMATURE

    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if held_part not in HELD_PARTS:
        raise ValueError(f"held part must be one of {HELD_PARTS}, got {held_part!r}")
    topic = joint_state_topic(bag, arm)
    states = load_joint_states(bag, topic)
    part, part_source = held_part, "given (--held-part)"
    task, contact = recorded_task_of(bag, topic)
    if held_part == "auto":
        if task == "block":
            raise NoJointStatesError(f"{topic} is the block task's (two slide joints, no arm)")
        learned = next((str(m.held_part) for m in policies(bag) if getattr(m, "held_part", "")), "")
        if learned:
            part, part_source = learned, "the recorded policy's law"
        elif task is None:
            part, part_source = "gear", "no task status in the bag: the drivers' default held part"
        else:
            part, part_source = _task_part(task), f"the recorded task {task!r}"
    values = np.broadcast_to(np.asarray(JOINT_ARMATURE if armature is None else armature, float), (7,)).copy()
    arm_, kind = arm_model(model, states.names, urdf, part, values)
    drivers = recorded_drivers(bag) if effort == "auto" else {}
    fit = identify(states, arm_, effort, drivers, min_speed, window, min_samples, effort_delay)
    warnings = [f"{j.name}: not identified: {j.reason}" for j in fit.joints if not j.identified]
    warnings += [f"{j.name}: negative friction (Coulomb {j.coulomb:.3g} Nm, viscous {j.viscous:.3g} Nm s/rad) is not "
                 f"friction alone: contact or another external force, a model or an effort error"
                 for j in fit.joints if j.identified and min(j.coulomb, j.viscous) < -NEGATIVE]
    if contact > CONTACT:
        warnings.append(f"the held part touched something (task status contact force up to {contact:.3g} N): "
                        f"contact forces are in the residual; identify from free-space motion")
    rms, chosen = fit.residual_rms, fit.effort
    other = next(k for k in rms if k != chosen)
    if rms[chosen] > 2.0 * rms[other]:
        warnings.append(f"the residual is {rms[chosen] / rms[other]:.1f}x smaller with effort {other!r} than with "
                        f"{chosen!r} ({rms[other]:.3g} vs {rms[chosen]:.3g} Nm): check --effort")
    return FrictionResult(str(bag), topic, kind, urdf or SPECS[kind].urdf_path(), part, part_source, values.tolist(),
                          min_speed, fit, warnings)


# ---------------------------------------------------------------------- output
def format_report(result: FrictionResult) -> str:
    """The per-joint table and what it assumed, for the terminal."""
    fit = result.fit
    lines = [f"friction from {result.topic} in {result.bag}: {fit.states} states at {fit.rate_hz:.0f} Hz, "
             f"{fit.segments} segment(s), {fit.samples} with a full {fit.window * 1e3:.0f} ms window",
             f"model: {result.model} ({result.urdf}), held part {result.held_part} ({result.held_part_source}), "
             f"armature {result.armature} kg m^2",
             f"effort: {fit.effort} ({fit.effort_source}); residual RMS before the fit: "
             + ", ".join(f"{k} {v:.3g} Nm" for k, v in fit.residual_rms.items()),
             "",
             f"{'joint':<14} {'Coulomb Nm':>10} {'viscous Nm s/rad':>16} {'offset Nm':>9} {'samples':>8} "
             f"{'outliers':>8} {'residual RMS Nm':>15} {'R^2':>6}"]
    for j in result.joints:
        if j.identified:
            lines.append(f"{j.name:<14} {j.coulomb:>10.4f} {j.viscous:>16.4f} {j.offset:>9.4f} {j.samples:>8d} "
                         f"{j.outliers:>8d} {j.rms:>15.4f} {j.r2:>6.3f}")
        else:
            lines.append(f"{j.name:<14} {'-':>10} {'-':>16} {'-':>9} {j.samples:>8d} {j.outliers:>8d} {'-':>15} "
                         f"{'-':>6}")
    lines += ["", f"friction opposes motion: torque on the joint -(Coulomb sign(dq) + viscous dq); fitted over "
                  f"|dq| > {result.min_speed:g} rad/s as effort - model = Coulomb sign(dq) + viscous dq + offset"]
    p = result.sim_parameters()
    as_list = {k: "[" + ",".join(repr(float(v)) for v in values) + "]" for k, values in p.items()}
    lines.append("the MuJoCo sim with this friction (joint_viscous adds to its own damping 0.05-0.1 Nm s/rad): "
                 f"-p sim_bridge:joint_friction:={as_list['joint_friction']} "
                 f"-p sim_bridge:joint_viscous:={as_list['joint_viscous']}")
    lines += [f"WARNING: {w}" for w in result.warnings]
    return "\n".join(lines)


def _armature(text: str) -> list[float]:
    values = [float(v) for v in text.replace(",", " ").split()]
    if len(values) not in (1, 7) or not all(np.isfinite(values)) or min(values) < 0.0:
        raise argparse.ArgumentTypeError(f"one value or 7, finite and >= 0: {text!r}")
    return values


def main(argv: list[str] | None = None) -> int:
    """Identify each joint's Coulomb and viscous friction from a bag's joint states and print them.
    Exit 0: every joint identified; 1: some joints did not move enough (warned, no number); 2: no
    joint states, an unreadable bag or a bad option."""
    parser = argparse.ArgumentParser(prog="python -m nf_bags.friction", description=main.__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("bag", help="bag directory or .mcap file")
    parser.add_argument("--json", type=Path, help="also write the result here (JSON)")
    parser.add_argument("--min-speed", type=float, default=0.05, help="rad/s: fit only samples moving faster")
    parser.add_argument("--min-samples", type=int, default=50,
                        help="samples needed each way per joint (default 50)")
    parser.add_argument("--window", type=float, default=0.02,
                        help="s: Savitzky-Golay window (default 0.02; at least 5 samples)")
    parser.add_argument("--model", choices=MODELS, default="auto", help="arm description (auto: by joint names)")
    parser.add_argument("--urdf", help="a description file instead of the arm's default (same joint names)")
    parser.add_argument("--held-part", choices=HELD_PARTS, default="auto",
                        help="part in the hand (auto: from the recorded task, else gear)")
    parser.add_argument("--armature", type=_armature, help="rotor armature, kg m^2: one value or 7 "
                        "(default: the controller's, panda_spec.JOINT_ARMATURE)")
    parser.add_argument("--effort", choices=EFFORTS, default="auto",
                        help="what joint_states.effort holds: applied (the MuJoCo sim) or no-gravity (the Franka "
                             "driver: the command the robot adds g(q) to); auto: the bag's /diagnostics, else the data")
    parser.add_argument("--effort-delay", type=float, help="s the effort lags its stamp (default: 0.001 for "
                        "applied, the sim's physics step; 0 for no-gravity)")
    parser.add_argument("--arm", help="the arm's namespace in a bag of several (/arm0)")
    args = parser.parse_args(argv)
    try:
        result = identify_bag(args.bag, arm=args.arm, model=args.model, urdf=args.urdf, held_part=args.held_part,
                              armature=args.armature, effort=args.effort, min_speed=args.min_speed,
                              window=args.window, min_samples=args.min_samples, effort_delay=args.effort_delay)
    except (BagError, NoJointStatesError, ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_report(result))
    if args.json:
        args.json.write_text(json.dumps(result.as_dict(), indent=1))
        print(f"written: {args.json}")
    return 0 if result.identified else 1


if __name__ == "__main__":
    raise SystemExit(main())
