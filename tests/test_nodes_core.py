"""ROS-free cores of the two nodes: the sim bridge (command checks, timeout, safe hold, clock)
and the controller's control loop (joint names, bad input, stamps, watchdog, policy swaps)."""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np
import pytest

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import (
    MODE_IDLE,
    MODE_RUNNING,
    MODE_SAFE_HOLD,
    NO_POLICY,
    ControlLoop,
    JointMap,
    JointStateError,
    LatencyStats,
    LoopConfig,
)
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core.flow_spec import FlowArchitecture
from nf_core.panda_spec import JOINT_NAMES, TORQUE_LIMITS
from nf_core.policy_params import PolicyParameterError, PolicyParameters
from nf_core.topics import parse_stamp_label, stamp_label
from sim_bridge_node.bridge import ACCEPTED, BAD, STALE, BridgeConfig, SimBridge
from sim_bridge_node.env import InsertionEnv

NAMES = list(JOINT_NAMES)


# ---------------------------------------------------------------------------- sim bridge
@pytest.fixture(scope="module")
def free_env() -> InsertionEnv:
    return InsertionEnv("free")


def _bridge(env: InsertionEnv, **kw) -> SimBridge:
    bridge = SimBridge(env, BridgeConfig(**kw))
    bridge.reset()
    return bridge


def test_bridge_gravity_matches_pinocchio(free_env):
    """The driver's gravity torque against an independent model (Pinocchio, same URDF and gear)."""
    bridge = _bridge(free_env)
    arm = ArmModel()
    for seed in range(3):
        bridge.reset(seed=seed)
        arm.kinematics(free_env.q)
        np.testing.assert_allclose(bridge.gravity(), arm.g, atol=1e-6)


@pytest.mark.parametrize("bad", [[0.0] * 6, [0.0] * 8, [0.0] * 6 + [np.nan], [np.inf] + [0.0] * 6, []])
def test_bridge_ignores_bad_commands_without_stepping(free_env, bad):
    bridge = _bridge(free_env, mode="lockstep")
    q, t = free_env.q, free_env.time
    assert bridge.accept_command(bad, now=0.0) == BAD
    assert "values, expected 7" in bridge.last_error or "NaN/Inf" in bridge.last_error
    assert bridge.bad_commands == 1 and not bridge.has_command
    assert not bridge.step_commanded()
    np.testing.assert_array_equal(free_env.q, q)
    assert free_env.time == t


def test_bridge_lockstep_steps_once_per_command(free_env):
    bridge = _bridge(free_env, mode="lockstep")
    t0 = bridge.sim_time
    for _ in range(3):
        assert bridge.accept_command(bridge.gravity(), now=0.0, answers=bridge.stamp_ns) == ACCEPTED
        assert bridge.step_commanded()
        assert not bridge.step_commanded(), "a command is used once"
    assert bridge.steps == 3
    assert bridge.sim_time == pytest.approx(t0 + 3 * bridge.dt)


def test_bridge_lockstep_drops_replies_to_earlier_states(free_env):
    """A reply duplicated by a resend (same stamp twice) must not be applied to the next state."""
    bridge = _bridge(free_env, mode="lockstep")
    first = bridge.stamp_ns
    assert bridge.accept_command(bridge.gravity(), 0.0, answers=first) == ACCEPTED
    bridge.step_commanded()
    assert bridge.accept_command(bridge.gravity(), 0.0, answers=first) == STALE
    assert not bridge.has_command and bridge.stale_commands == 1 and bridge.bad_commands == 0
    assert bridge.accept_command(bridge.gravity(), 0.0) == ACCEPTED, "unlabelled commands answer the current state"
    assert parse_stamp_label(stamp_label(first)) == first
    assert parse_stamp_label("joints") is None and parse_stamp_label("state_stamp_ns=x") is None
    realtime = _bridge(free_env, mode="realtime")
    assert realtime.accept_command(np.zeros(7), 0.0, answers=1) == ACCEPTED, "realtime ignores the label"


def _drift_deg(bridge: SimBridge, steps: int, now: float = 0.0, command: np.ndarray | None = None) -> float:
    q0 = bridge.env.q
    for _ in range(steps):
        if command is not None:
            bridge.accept_command(command, now)
            bridge.step_commanded()
        else:
            bridge.step_realtime(now)
    return float(np.degrees(np.max(np.abs(bridge.env.q - q0))))


def test_bridge_realtime_timeout_enters_safe_hold_that_holds_the_arm(free_env):
    bridge = _bridge(free_env, mode="realtime", command_timeout=0.05)
    assert bridge.step_realtime(0.0), "no command yet: hold"
    assert bridge.command_timeouts == 0
    zero = np.zeros(7)
    bridge.accept_command(zero, now=1.0)
    assert not bridge.step_realtime(1.04), "a fresh command is applied"
    np.testing.assert_array_equal(bridge.torque, zero)
    assert bridge.step_realtime(1.06), "older than the timeout: hold"
    assert bridge.command_timeouts == 1
    assert bridge.step_realtime(1.5) and bridge.command_timeouts == 1, "one timeout per silence"
    bridge.reset()
    assert _drift_deg(bridge, 1000, now=5.0) < 0.01, "gravity compensation + damping holds the arm for 1 s"
    bridge.reset()
    assert _drift_deg(bridge, 300, command=zero) > 3.0, "without it the arm falls (the check is not vacuous)"


def _coast(bridge: SimBridge, seconds: float = 1.5) -> tuple[float, float]:
    """From a moving arm (0.6 rad/s on joints 1, 2 and 4) with no command at all: the largest and the
    final joint distance (rad) from where the hold began."""
    env = bridge.env
    env.data.qvel[:7] = [0.6, 0.6, 0.0, 0.6, 0.0, 0.0, 0.0]
    mujoco.mj_forward(env.model, env.data)
    q0, far = env.q.copy(), 0.0
    for k in range(round(seconds / bridge.dt)):
        assert bridge.step_realtime(10.0 + k * bridge.dt)
        far = max(far, float(np.abs(env.q - q0).max()))
    return far, float(np.abs(env.q - q0).max())


def test_bridge_safe_hold_with_stiffness_brakes_where_it_began(free_env):
    """The driver-side hold with a joint spring stops the arm where its commands stopped, as a robot
    brakes; damping alone lets it coast (hold_stiffness 0, the default)."""
    coast_far, _ = _coast(_bridge(free_env, mode="realtime", hold_damping=2.0))
    brake_far, brake_end = _coast(_bridge(free_env, mode="realtime", hold_damping=15.0, hold_stiffness=100.0))
    print(f"0.6 rad/s into the hold: damping 2 coasts {coast_far:.3f} rad; spring 100 + damping 15 stops "
          f"within {brake_far:.3f} rad and ends {brake_end:.4f} rad from where it began")
    assert coast_far > 0.2  # measured 0.27 rad
    assert brake_far < 0.1 and brake_end < 0.02  # measured 0.025 rad and 0.0005 rad
    bridge = _bridge(free_env, mode="realtime", command_timeout=0.05, hold_stiffness=100.0, hold_damping=15.0)
    bridge.accept_command(bridge.gravity(), now=0.0)
    assert not bridge.step_realtime(0.01)
    bridge.env.data.qpos[0] += 0.05  # the arm was elsewhere when commands stopped: the anchor is there
    mujoco.mj_forward(bridge.env.model, bridge.env.data)
    q_stop = bridge.env.q.copy()
    for k in range(500):
        bridge.step_realtime(1.0 + k * 0.001)
    assert float(np.abs(bridge.env.q - q_stop).max()) < 0.02


def test_bridge_driver_gravity_compensation(free_env):
    bridge = _bridge(free_env, mode="lockstep", driver_gravity_compensation=True)
    assert _drift_deg(bridge, 500, command=np.zeros(7)) < 0.01
    np.testing.assert_allclose(bridge.torque, bridge.gravity(), atol=1e-6)
    np.testing.assert_allclose(bridge.effort, 0.0, atol=1e-6)  # effort: the command's part, as Franka's
    command = np.array([1.0, -2.0, 0.5, 3.0, -0.5, 0.2, 0.0])
    assert bridge.step_with(command)
    np.testing.assert_allclose(bridge.effort, command, atol=1e-9)
    assert bridge.torque[1] != pytest.approx(command[1], abs=0.1)  # the applied torque carries gravity


def test_bridge_hold_effort_leaves_out_the_drivers_gravity(free_env):
    """At rest the safe hold applies gravity: effort reports it, unless the driver adds gravity itself."""
    for driver_gravity in (False, True):
        bridge = _bridge(free_env, mode="realtime", command_timeout=0.05, driver_gravity_compensation=driver_gravity)
        bridge.reset(seed=0)
        assert bridge.step_realtime(0.0)  # no command yet: the safe hold, from rest
        assert np.abs(bridge.torque).max() > 1.0
        if driver_gravity:
            np.testing.assert_allclose(bridge.effort, 0.0, atol=1e-9)
        else:
            np.testing.assert_array_equal(bridge.effort, bridge.torque)


def test_bridge_reset_keeps_the_clock_running_and_refuses_bad_starts(free_env):
    bridge = _bridge(free_env, mode="lockstep")
    for _ in range(5):
        bridge.accept_command(bridge.gravity(), 0.0)
        bridge.step_commanded()
    before = bridge.sim_time
    bridge.reset(seed=4)
    assert bridge.sim_time > before and free_env.time == 0.0
    q, t = free_env.q, bridge.sim_time
    with pytest.raises(ValueError, match="start configuration"):
        bridge.reset(q=np.zeros(3))
    with pytest.raises(ValueError, match="joint limits"):
        bridge.reset(q=np.full(7, 3.5))
    np.testing.assert_array_equal(free_env.q, q)
    assert bridge.sim_time == t


@pytest.mark.parametrize("kw", [{"mode": "fast"}, {"command_timeout": 0.0}, {"hold_damping": -1.0},
                                {"hold_stiffness": -1.0}, {"hold_stiffness": float("nan")},
                                {"command_timeout": float("nan")}])
def test_bridge_config_refuses_bad_values(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        BridgeConfig(**kw).check()


# ---------------------------------------------------------------------------- control loop
Q0 = np.array([0.0, -0.121374, 0.0, -2.258102, 0.0, 2.136727, 0.785398])  # the gear scene start
REST = np.zeros(7)


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel()


def _params(arm: ArmModel, version: int = 1, dim: int = 3) -> PolicyParameters:
    arch = FlowArchitecture(dim=dim, n_flow=1, n_hidden=8, activation="gelu")
    weights = np.random.default_rng(version).uniform(-0.3, 0.3, arch.n_params)
    x_ref = (arm.tcp_position(Q0) + [0.05, 0.0, -0.1])[:dim]
    return PolicyParameters(arch, weights, np.zeros(1), 40 * np.eye(dim), 20 * np.eye(dim), x_ref, version=version)


def _loop(arm: ArmModel, policy: bool = True, **cfg) -> ControlLoop:
    loop = ControlLoop(arm, config=LoopConfig(**cfg))
    if policy:
        assert loop.set_policy(_params(arm))
    return loop


class _Feed:
    """Joint states with increasing stamps (1 ms apart) into a loop."""

    def __init__(self, loop: ControlLoop) -> None:
        self.loop, self.stamp = loop, 0

    def __call__(self, names=NAMES, q=Q0, dq=REST, stamp=None, now=0.0):
        self.stamp += 1_000_000
        return self.loop.on_joint_state(names, list(q), list(dq), self.stamp if stamp is None else stamp, now)


def _safe(tau: np.ndarray) -> bool:
    return tau.shape == (7,) and bool(np.all(np.isfinite(tau))) and bool(np.all(np.abs(tau) <= TORQUE_LIMITS))


def test_joint_map_reorders_by_name_and_rejects_bad_names():
    jm = JointMap()
    order = [3, 0, 6, 1, 5, 2, 4]
    q, dq = jm.map([NAMES[i] for i in order], Q0[order], np.arange(7.0)[order])
    np.testing.assert_array_equal(q, Q0)
    np.testing.assert_array_equal(dq, np.arange(7.0))
    for names, match in (([*NAMES[:6], "elbow"], "unknown"), (NAMES[:6], "missing"),
                         ([*NAMES[:6], NAMES[0]], "duplicate"), ([*NAMES, "panda_finger_joint1"], "unknown")):
        with pytest.raises(JointStateError, match=match):
            jm.map(names, np.zeros(len(names)), np.zeros(len(names)))
    with pytest.raises(JointStateError, match="7 names but 6 positions"):
        jm.map(NAMES, np.zeros(6), np.zeros(7))


def test_joint_map_checks_a_drivers_name_tuple_once_and_still_maps_by_name():
    """A hosting driver passes the same tuple every tick (checked once, then reused); another order,
    a list in between or a size mismatch still gets the full check."""
    jm = JointMap()
    order = [3, 0, 6, 1, 5, 2, 4]
    shuffled = tuple(NAMES[i] for i in order)
    for _ in range(2):  # the second call takes the cached path
        q, dq = jm.map(shuffled, Q0[order], np.arange(7.0)[order])
        np.testing.assert_array_equal(q, Q0)
        np.testing.assert_array_equal(dq, np.arange(7.0))
    q, _ = jm.map(list(NAMES), Q0, np.zeros(7))  # a topic's list in between: identity order
    np.testing.assert_array_equal(q, Q0)
    q, _ = jm.map(shuffled, Q0[order], np.zeros(7))  # the tuple again: re-checked, still reordered
    np.testing.assert_array_equal(q, Q0)
    with pytest.raises(JointStateError, match="7 names but 6 positions"):
        jm.map(shuffled, np.zeros(6), np.zeros(7))
    same = tuple(NAMES)
    jm.map(same, Q0, np.zeros(7))
    q, _ = jm.map(same, Q0 + 0.1, np.zeros(7))
    np.testing.assert_array_equal(q, Q0 + 0.1)


def test_loop_holds_until_a_policy_arrives(arm):
    loop = _loop(arm, policy=False)
    feed = _Feed(loop)
    tau, new = feed()
    assert new == "" and loop.mode == MODE_SAFE_HOLD and loop.fault == NO_POLICY
    arm.kinematics(Q0)
    np.testing.assert_allclose(tau, arm.g, atol=1e-9)  # at rest the hold is gravity compensation
    assert loop.set_policy(_params(arm, version=3))
    tau, new = feed()
    assert new == "" and loop.mode == MODE_IDLE and loop.policy_version == 3 and _safe(tau)
    assert np.isfinite(loop.lyapunov()[0])


def test_loop_same_torque_for_any_name_order(arm):
    a, b = _loop(arm), _loop(arm)
    order = [6, 5, 4, 3, 2, 1, 0]
    dq = np.linspace(-0.1, 0.1, 7)
    tau_a = _Feed(a)(q=Q0, dq=dq)[0].copy()
    tau_b = _Feed(b)(names=[NAMES[i] for i in order], q=Q0[order], dq=dq[order])[0]
    np.testing.assert_allclose(tau_a, tau_b, atol=1e-12)


BAD_STATES = {
    "nan position": dict(q=np.where(np.arange(7) == 2, np.nan, Q0)),
    "inf velocity": dict(dq=np.where(np.arange(7) == 5, np.inf, 0.0)),
    "short position": dict(q=Q0[:6]),
    "unknown name": dict(names=[*NAMES[:6], "elbow_joint"]),
    "missing name": dict(names=NAMES[:6], q=Q0[:6], dq=np.zeros(6)),
    "out of range": dict(q=np.where(np.arange(7) == 0, 7.0, Q0)),
}


@pytest.mark.parametrize("kind", BAD_STATES)
def test_loop_bad_joint_state_latches_safe_hold(arm, kind):
    loop = _loop(arm)
    feed = _Feed(loop)
    feed(dq=np.full(7, 0.05))
    tau, new = feed(**BAD_STATES[kind])
    assert _safe(tau) and new and loop.mode == MODE_SAFE_HOLD and loop.fault == new
    assert loop.faults == 1
    for _ in range(3):  # valid states do not re-arm by themselves
        tau, again = feed()
        assert _safe(tau) and again == "" and loop.fault == new
    arm.kinematics(Q0)
    np.testing.assert_allclose(tau, arm.g, atol=1e-6)  # at rest the hold is gravity compensation
    assert loop.clear_fault() == new
    feed()
    assert loop.mode == MODE_IDLE and loop.fault == ""


def test_loop_rejects_out_of_order_stamps_but_answers_repeats(arm):
    loop = _loop(arm)
    feed = _Feed(loop)
    feed(stamp=5_000_000)
    _, new = feed(stamp=5_000_000)  # a repeated state (lockstep resend) is answered normally
    assert new == "" and loop.mode == MODE_IDLE
    tau, new = feed(stamp=4_000_000)
    assert "out of order" in new and loop.mode == MODE_SAFE_HOLD and _safe(tau)


def test_loop_stale_state_watchdog(arm):
    loop = _loop(arm, state_timeout=0.02)
    feed = _Feed(loop)
    assert loop.on_timer(now=5.0) == (None, ""), "no state yet: nothing to hold"
    feed(now=10.0)
    assert loop.on_timer(now=10.015) == (None, "")
    assert loop.on_timer(now=10.05) == (None, ""), "the watchdog itself was starved: states may be queued"
    tau, new = loop.on_timer(now=10.055)
    assert tau is not None and _safe(tau) and "stale" in new and loop.mode == MODE_SAFE_HOLD
    assert loop.on_timer(now=10.06)[1] == "", "reported once"
    late = _loop(arm, state_timeout=0.02)
    late_feed = _Feed(late)
    late_feed(now=10.0)
    late.on_timer(now=10.005)
    assert late.on_timer(now=10.6) == (None, ""), "after its own 595 ms stall the watchdog waits a run"
    late_feed(now=10.601)  # the queued states are read
    assert late.on_timer(now=10.605) == (None, "") and late.mode != MODE_SAFE_HOLD
    off = _loop(arm)
    _Feed(off)(now=0.0)
    assert off.on_timer(now=100.0) == (None, ""), "state_timeout 0 disables the watchdog (lockstep)"


def test_loop_consecutive_deadline_misses_latch(arm):
    loop = _loop(arm, deadline=0.001, max_consecutive_misses=3)
    for seconds in (0.002, 0.002, 0.0005, 0.002, 0.002):
        assert loop.record_latency(seconds) == ""
    assert "3 consecutive deadline misses" in loop.record_latency(0.003)
    assert loop.deadline_misses == 5 and loop.mode == MODE_SAFE_HOLD


def test_loop_policy_checks_and_swaps_between_episodes(arm):
    loop = _loop(arm)
    with pytest.raises(PolicyParameterError, match="3-D"):
        loop.set_policy(_params(arm, dim=2))
    assert loop.policy_version == 1
    loop.episode_active = True
    assert loop.mode == MODE_RUNNING
    assert not loop.set_policy(_params(arm, version=2)), "queued while an episode runs"
    assert loop.policy_version == 1
    loop.end_episode()
    assert loop.policy_version == 2 and loop.mode == MODE_IDLE


def test_latency_stats_percentiles():
    stats = LatencyStats(capacity=1000)
    for us in range(1, 101):
        stats.add(us * 1e-6)
    report = stats.report()
    assert report["count"] == 100 and report["max_us"] == pytest.approx(100.0)
    assert report["p50_us"] == pytest.approx(50.5) and report["p99_us"] == pytest.approx(99.01)
    assert stats.report()["count"] == 0
    assert stats.total == 100


# ---------------------------------------------------------------------------- configuration
@pytest.mark.parametrize("task", ["gear", "peg", "block"])
def test_config_node_sections_match_declared_parameters(task):
    """Every node setting in config/<task>.yaml is a declared parameter of the same type (rclpy
    refuses a YAML 1 for a float parameter), and the shared task name is one the sim knows."""
    import yaml

    from nf_controller_node import node as controller_node
    from sim_bridge_node import node as sim_node
    from sim_bridge_node.scenes import TASKS

    doc = yaml.safe_load((Path(__file__).parents[1] / "config" / f"{task}.yaml").read_text())
    assert doc["/**"]["ros__parameters"]["task"] in TASKS
    # sections named /**/<node>: they apply to the node in any namespace (an arm of many)
    sections = (("/**/sim_bridge", sim_node.PARAMETERS), ("/**/nf_controller", controller_node.PARAMETERS))
    for section, declared in sections:
        for key, value in doc.get(section, {}).get("ros__parameters", {}).items():
            assert key in declared, f"{task}.yaml: {section}.{key} is not a parameter of the node"
            assert type(value) is type(declared[key][0]), f"{task}.yaml: {section}.{key} has type {type(value)}"


def test_loop_rate_limit_starts_from_the_applied_torque(arm):
    loop = _loop(arm)
    applied = np.array([5.0, -20.0, 3.0, 10.0, 1.0, -2.0, 0.5])
    order = list(reversed(NAMES))  # the driver's own name order
    assert loop.start_from_applied(order, applied[::-1].tolist()) == ""
    tau, _ = _Feed(loop)()
    step = loop.controller.law.max_step
    assert np.all(np.abs(tau - applied) <= step + 1e-9), tau  # the first command ramps from the arm's torque
    assert loop.start_from_applied(NAMES, applied.tolist()) == "the controller has commanded already"


def test_a_measured_effort_with_gravity_seeds_the_command_part(arm):
    """franka_ros2's effort is the measured joint torque, gravity included; when the driver adds gravity
    (gravity_compensation false) the controller seeds its rate limit from that torque less g(q)."""
    loop = ControlLoop(arm, TorqueLawConfig(gravity_compensation=False))
    assert loop.set_policy(_params(arm))
    command = np.array([5.0, -20.0, 3.0, 10.0, 1.0, -2.0, 0.5])
    g = arm.gravity(np.asarray(Q0, dtype=float)).copy()
    assert np.abs(g).max() > 5.0  # the gravity a wrong reading would step by
    assert loop.start_from_applied(NAMES, (command + g).tolist(), list(Q0)) == ""
    np.testing.assert_allclose(loop.controller.tau_prev, command, atol=1e-9)


@pytest.mark.parametrize("effort, why", [([], "no effort"), ([1.0] * 6, "not usable"),
                                         ([float("nan")] + [0.0] * 6, "not finite"), ([500.0] + [0.0] * 6, "limits")])
def test_loop_refuses_an_unusable_applied_torque(arm, effort, why):
    loop = _loop(arm)
    assert why in loop.start_from_applied(NAMES, effort)
    assert np.all(np.isnan(loop.controller.tau_prev))  # unprimed, as without a report
