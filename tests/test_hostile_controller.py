"""Hostile input against the controller's ROS-free core (issue 16, items 1-5 and 7; issue 15's
Lyapunov dt): every fault is clearable, the torque rate limit holds at every tick, implausible
states fault in every mode and never drive the hold, rejections are counted and reported from a
slow timer, and every fault text is bounded."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nf_controller_node import control_loop
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import MODE_IDLE, MODE_SAFE_HOLD, ControlLoop, LoopConfig
from nf_controller_node.lyapunov import LyapunovMonitor
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import episode, panda_spec
from nf_core.episode import EpisodeRun, EpisodeSpec
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters

# The names the fixes added are looked up when a test runs (so that, against the code before the
# fixes, each test fails on its own instead of the whole module failing to import).
FAULT_TEXT_MAX = 300  # control_loop.FAULT_TEXT_MAX, checked in test_bound_text

NAMES = list(panda_spec.JOINT_NAMES)
Q0 = np.array([0.0, -0.121374, 0.0, -2.258102, 0.0, 2.136727, 0.785398])
REST = np.zeros(7)
FAR_FUTURE_NS = (2**31 - 1) * 1_000_000_000  # sec = 2^31 - 1
MAX_STEP = panda_spec.TORQUE_RATE_LIMIT * 0.001  # Nm per 1 ms tick


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel()


def _params(arm: ArmModel, version: int = 1, offset=(0.05, 0.0, -0.1), stiffness: float = 40.0) -> PolicyParameters:
    arch = FlowArchitecture(dim=3, n_flow=1, n_hidden=8, activation="gelu")
    weights = np.random.default_rng(version).uniform(-0.3, 0.3, arch.n_params)
    x_ref = arm.tcp_position(Q0) + np.asarray(offset)
    return PolicyParameters(arch, weights, np.zeros(1), stiffness * np.eye(3), 20 * np.eye(3), x_ref, version=version)


def _loop(arm: ArmModel, policy: bool = True, **cfg) -> ControlLoop:
    loop = ControlLoop(arm, config=LoopConfig(**cfg))
    if policy:
        assert loop.set_policy(_params(arm))
    return loop


class _Feed:
    """Joint states with increasing stamps (1 ms apart); keeps every torque answered."""

    def __init__(self, loop: ControlLoop, stamp: int = 0) -> None:
        self.loop, self.stamp, self.taus = loop, stamp, []

    def __call__(self, names=NAMES, q=Q0, dq=REST, stamp=None):
        if stamp is None:
            self.stamp += 1_000_000
            stamp = self.stamp
        tau, new = self.loop.on_joint_state(names, list(q), list(dq), stamp, 0.0)
        self.taus.append(tau.copy())
        return tau, new


def _gravity(arm: ArmModel, q: np.ndarray) -> np.ndarray:
    arm.kinematics(q)
    return arm.g.copy()


# ---------------------------------------------------------------------------- item 1
def test_far_future_stamp_fault_clears_and_normal_states_run_again(arm):
    loop = _loop(arm)
    feed = _Feed(loop)
    feed()
    _, new = feed(stamp=FAR_FUTURE_NS)  # an otherwise valid state, sec = 2^31 - 1
    _, new = feed()
    assert "out of order" in new and loop.mode == MODE_SAFE_HOLD
    assert loop.clear_fault().startswith("joint state out of order")
    for _ in range(5):
        _, new = feed()
        assert new == "" and loop.fault == "" and loop.mode == MODE_IDLE, loop.fault
    assert loop.bad_inputs == 1


@pytest.mark.parametrize("bad", [dict(q=np.full(7, np.nan)), dict(dq=np.r_[REST[:3], 1e6, REST[4:]]),
                                 dict(names=[*NAMES[:6], "elbow"])])
def test_a_rejected_state_does_not_move_the_loops_time(arm, bad):
    """A state that faults (NaN, implausible, unknown name) stamped far in the future must not make
    the normal states after it "out of order"."""
    loop = _loop(arm)
    feed = _Feed(loop)
    feed()
    _, new = feed(stamp=FAR_FUTURE_NS, **bad)
    assert new and loop.bad_inputs == 1
    for _ in range(5):
        feed()
    assert loop.bad_inputs == 1, loop.last_rejection
    assert loop.clear_fault()
    feed()
    assert loop.fault == ""


def test_clear_fault_after_a_driver_restart_with_its_clock_back_at_zero(arm):
    loop = _loop(arm)
    feed = _Feed(loop, stamp=10**12)
    feed()
    feed.stamp = 0  # the driver restarted
    _, new = feed()
    assert "out of order" in new
    loop.clear_fault()
    for _ in range(3):
        _, new = feed()
        assert new == "" and loop.fault == ""


# ---------------------------------------------------------------------------- item 2
def _spec(x_goal: np.ndarray, sigma: float = 30.0, duration: float = 0.05) -> EpisodeSpec:
    return EpisodeSpec(episode_id=1, policy_version=1, duration=duration, decision_period=0.01, control_period=0.001,
                       sigma=np.full(3, sigma), noise_seed=4, x_goal=x_goal)


@pytest.mark.parametrize("idle_mode", ["hold", "policy"])
def test_rate_limit_holds_at_every_tick_across_an_episode_without_world_reset(arm, idle_mode):
    """Hardware (no reset service): the first command of an episode is rate-limited against the
    idle command before it, as is every later one, and the hold after the episode."""
    loop = _loop(arm, idle_mode=idle_mode)
    feed = _Feed(loop)
    for _ in range(50):  # the idle command settles
        feed()
    run = EpisodeRun(_spec(loop.policy.x_ref))
    loop.start_episode(run, feed.stamp + 1)  # default: the world was not reset
    while not run.done:
        _, new = feed()
        assert new == ""
    loop.end_episode()
    for _ in range(20):
        feed()
    steps = np.abs(np.diff(np.array(feed.taus), axis=0)).max(axis=1)
    assert steps.max() <= MAX_STEP + 1e-9, f"largest step {steps.max():.3f} Nm at tick {int(steps.argmax())}"
    assert run.steps > 0


def test_world_reset_episode_starts_without_rate_limit(arm):
    """A simulator that teleported the arm asks for it (the trainer's rollout does the same)."""
    loop = _loop(arm, idle_mode="hold")
    feed = _Feed(loop)
    for _ in range(50):
        feed()
    run = EpisodeRun(_spec(loop.policy.x_ref))
    loop.start_episode(run, feed.stamp + 1, world_was_reset=True)
    feed()
    jump = np.abs(feed.taus[-1] - feed.taus[-2]).max()
    assert jump > MAX_STEP + 0.5, "the first command is the law's, not limited"
    while not run.done:  # later commands are limited again
        feed()
    steps = np.abs(np.diff(np.array(feed.taus[50:]), axis=0)).max(axis=1)
    assert steps.max() <= MAX_STEP + 1e-9


# ---------------------------------------------------------------------------- item 3
@pytest.mark.parametrize("idle_mode", ["hold", "policy"])
def test_absurd_velocity_faults_and_never_drives_the_hold(arm, idle_mode):
    loop = _loop(arm, idle_mode=idle_mode)
    feed = _Feed(loop)
    for _ in range(30):
        feed()
    g = _gravity(arm, Q0)
    for i in range(200):
        tau, new = feed(dq=np.r_[REST[:3], 1e6, REST[4:]])
        assert (new != "") == (i == 0)
        assert np.all(np.isfinite(tau))
    assert "velocity implausible" in loop.fault and "panda_joint4" in loop.fault
    assert loop.bad_inputs == 200 and loop.faults == 1
    np.testing.assert_allclose(tau, g, atol=1e-6)  # the hold of the last valid state: gravity, no saturation


def test_rejection_keeps_the_values_of_the_rejected_state_not_of_the_drivers_buffer(arm):
    """A hosting driver may pass views of its own state buffers (the composed sim passes MuJoCo's
    arrays) and rewrite them before anyone reads why a state was rejected: the report must show the
    rejected values, not whatever the buffer holds later."""
    loop = _loop(arm)
    names = tuple(NAMES)
    q, dq = Q0.copy(), REST.copy()
    loop.on_joint_state(names, q, dq, 1_000_000, 0.0)
    dq[3] = 1e6
    loop.on_joint_state(names, q, dq, 2_000_000, 0.0)  # latches the hold (text formatted now)
    dq[3] = 2e6
    loop.on_joint_state(names, q, dq, 3_000_000, 0.0)  # rejected again: the text is formatted when read
    dq[3] = 0.5  # the driver's next (plausible) state, written into the same buffer
    assert "2e+06" in loop.last_rejection and "panda_joint4" in loop.last_rejection


def _mid_limits() -> np.ndarray:
    return 0.5 * (panda_spec.Q_MIN + panda_spec.Q_MAX)


IMPLAUSIBLE = {
    "q 1e300": (np.r_[1e300, Q0[1:]], REST, "position implausible"),
    "q beyond 2 pi": (np.r_[Q0[:2], 7.0, Q0[3:]], REST, "position implausible"),
    "q 10 deg past the limit": (np.r_[Q0[:3], panda_spec.Q_MAX[3] + math.radians(10), Q0[4:]], REST,
                                "position implausible"),
    "dq 12 x limit": (Q0, np.r_[REST[:6], 12.0 * panda_spec.DQ_MAX[6]], "velocity implausible"),
    "dq -1e6": (Q0, np.r_[-1e6, REST[1:]], "velocity implausible"),
    "q NaN": (np.r_[Q0[:5], np.nan, Q0[6]], REST, "not finite"),
    "dq -inf": (Q0, np.r_[REST[:4], -np.inf, REST[5:]], "not finite"),
}


@pytest.mark.parametrize("idle_mode", ["hold", "policy", "pause"])
@pytest.mark.parametrize("kind", IMPLAUSIBLE)
def test_implausible_states_fault_and_are_counted_in_every_mode(arm, idle_mode, kind):
    q, dq, match = IMPLAUSIBLE[kind]
    loop = _loop(arm, idle_mode=idle_mode)
    feed = _Feed(loop)
    feed()
    prev = feed()[0].copy()
    tau, new = feed(q=q, dq=dq)
    assert match in new and loop.bad_inputs == 1 and loop.mode == MODE_SAFE_HOLD
    # the hold of the last valid state (gravity at Q0, no damping), rate-limited from the last command
    np.testing.assert_allclose(tau, np.clip(_gravity(arm, Q0), prev - MAX_STEP, prev + MAX_STEP), atol=1e-6)
    assert loop.clear_fault()
    feed()
    assert loop.fault == ""


def test_states_within_the_margins_are_accepted(arm):
    loop = _loop(arm, idle_mode="hold")
    feed = _Feed(loop)
    near = np.r_[Q0[:3], panda_spec.Q_MAX[3] + math.radians(2), Q0[4:]]
    fast = 9.5 * panda_spec.DQ_MAX * np.sign(np.arange(7) - 3.5)
    for q, dq in ((near, REST), (Q0, fast), (panda_spec.Q_MIN, REST), (_mid_limits(), -fast)):
        _, new = feed(q=q, dq=dq)
        assert new == "" and loop.fault == ""
    assert loop.bad_inputs == 0


def test_no_policy_hold_checks_too(arm):
    loop = _loop(arm, policy=False)
    feed = _Feed(loop)
    feed()
    _, new = feed(q=np.r_[1e300, Q0[1:]])
    assert "implausible" in new and loop.bad_inputs == 1


# ---------------------------------------------------------------------------- item 4 (core side)
def test_rejections_are_counted_and_reported_once_from_the_slow_timer(arm):
    loop = _loop(arm)
    feed = _Feed(loop)
    assert loop.take_rejection_report() is None
    feed()
    for _ in range(30):
        feed(dq=np.full(7, np.nan))
    feed(names=["x"] * 7)
    report = loop.take_rejection_report()
    assert report is not None and report.startswith("31 joint state(s) rejected (31 in all)")
    assert "unknown joint name" in report and len(report) <= 2 * FAULT_TEXT_MAX
    assert loop.take_rejection_report() is None, "each rejection is reported once"
    loop.on_task_status(1e300, True)
    report = loop.take_rejection_report()
    assert report is not None and "1 task status message(s) rejected" in report and "joint state" not in report


# ---------------------------------------------------------------------------- item 5
def test_fault_text_is_bounded_for_twenty_thousand_unknown_names(arm):
    loop = _loop(arm)
    feed = _Feed(loop)
    feed()
    names = [f"hostile_joint_{i}" for i in range(20_000)]
    _, new = feed(names=names, q=np.zeros(20_000), dq=np.zeros(20_000))
    assert new and len(new) <= FAULT_TEXT_MAX and len(loop.fault) <= FAULT_TEXT_MAX
    assert "20000 names for 7 joints" in new
    assert len(loop.last_rejection) <= FAULT_TEXT_MAX
    loop.clear_fault()
    huge = ["n" * 1_000_000, *NAMES[1:]]  # one 1 MB name among the right count
    _, new = feed(names=huge)
    assert "unknown joint name" in new and len(new) <= FAULT_TEXT_MAX
    loop.clear_fault()
    _, new = feed(names=[*NAMES[:6], "unknown_1", "unknown_2", "unknown_3", "unknown_4", "unknown_5"],
                  q=np.zeros(11), dq=np.zeros(11))
    assert "and 2 more" in new and len(new) <= FAULT_TEXT_MAX


def test_bound_text():
    assert control_loop.FAULT_TEXT_MAX == FAULT_TEXT_MAX
    assert control_loop.bound_text("abc") == "abc"
    cut = control_loop.bound_text("x" * 5000)
    assert len(cut) == FAULT_TEXT_MAX and cut.endswith("chars]") and "+" in cut


# ---------------------------------------------------------------------------- item 7
@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("-inf"), float("inf"), 1e9, "5"])
def test_goal_duration_rejected(bad):
    with pytest.raises(ValueError, match="duration"):
        episode.check_goal_duration(bad if bad != "5" else object(), 5.0)


def test_goal_duration_zero_is_the_default():
    assert episode.check_goal_duration(0.0, 5.0) == 5.0
    assert episode.check_goal_duration(2.5, 5.0) == 2.5


@pytest.mark.parametrize("bad", [1e300, -1e300, float("nan"), float("inf"), 1.0, -2.0])
def test_task_depth_rejected_and_not_copied(arm, bad):
    with pytest.raises(ValueError, match="depth"):
        episode.check_task_depth(bad)
    loop = _loop(arm)
    assert loop.on_task_status(0.012, True) == ""
    reason = loop.on_task_status(bad, False)
    assert "depth" in reason and loop.bad_task_status == 1
    assert loop.depth == 0.012 and loop.task_success, "the spoofed status is not used"


def test_task_depth_accepted():
    assert episode.check_task_depth(0.0) == 0.0 and episode.check_task_depth(0.02) == 0.02


# ---------------------------------------------------------------------------- issue 15: Lyapunov dt
def test_lyapunov_rate_uses_the_real_time_between_calls(arm):
    loop = _loop(arm)
    feed = _Feed(loop)
    feed()
    v0, rate0 = loop.lyapunov(now=100.0)
    assert math.isfinite(v0) and rate0 == 0.0
    q1 = Q0 + 0.01
    feed(q=q1)
    v1 = loop.lyapunov_value()
    value, rate = loop.lyapunov(now=100.1)  # 100 ms later, not the assumed 20 ms
    tc = loop.monitor.time_constant
    alpha = 0.1 / (tc + 0.1)
    assert value == pytest.approx(v1)
    assert rate == pytest.approx(alpha * (v1 - v0) / 0.1, rel=1e-9)
    assert loop.lyapunov(now=100.1) == (pytest.approx(v1), rate), "same instant: no new sample"
    assert loop.monitor.samples == 2
    assert math.isfinite(loop.lyapunov()[1]), "now defaults to the monotonic clock"


def test_monitor_update_with_irregular_dt():
    m = LyapunovMonitor(dt=0.02, tolerance=1e-3, time_constant=0.1)
    m.update(1.0)
    rate = m.update(2.0, dt=0.5)
    assert rate == pytest.approx(0.5 / 0.6 * 2.0)
    m2 = LyapunovMonitor(dt=0.02, tolerance=1e-3, time_constant=0.1)
    m2.update(1.0)
    assert m2.update(2.0) == pytest.approx(0.02 / 0.12 * 50.0), "without dt: the constructor's"


# ---------------------------------------------------------------------------- all of it at once
def test_fuzz_torques_stay_finite_limited_and_rate_limited_and_every_fault_clears(arm):
    """A few thousand joint states, a third of them hostile (NaN, 1e300, 1e6 rad/s, beyond the
    limits, far-future or old stamps, unknown or huge name lists, wrong sizes), with an episode
    (no world reset) running through part of them: every torque is finite, within the torque
    limits and within one rate-limit step of the previous one, and every fault clears."""
    rng = np.random.default_rng(16)
    loop = _loop(arm, idle_mode="hold")
    feed = _Feed(loop)
    limits = panda_spec.TORQUE_LIMITS
    prev = feed()[0].copy()
    run = None
    faults_seen = 0
    for k in range(3000):
        if k == 500:
            run = EpisodeRun(_spec(loop.policy.x_ref, sigma=20.0, duration=1.0))
            loop.clear_fault()
            loop.start_episode(run, feed.stamp + 1)
        if run is not None and (run.done or loop.fault):
            loop.end_episode()
            run = None
        q = Q0 + rng.normal(0.0, 0.05, 7)
        dq = rng.normal(0.0, 0.3, 7)
        kind = rng.integers(0, 12)
        args: dict = {"q": q, "dq": dq}
        if kind == 0:
            args["q"] = np.where(rng.random(7) < 0.3, np.nan, q)
        elif kind == 1:
            args["q"] = q * 1e300
        elif kind == 2:
            args["dq"] = np.where(np.arange(7) == rng.integers(7), rng.choice([-1e6, 1e6]), dq)
        elif kind == 3:
            args["q"] = np.where(np.arange(7) == 3, panda_spec.Q_MAX[3] + rng.uniform(0.1, 3.0), q)
        elif kind == 4:
            args["stamp"] = FAR_FUTURE_NS + int(rng.integers(10**9))
        elif kind == 5:
            args["stamp"] = int(rng.integers(0, max(1, feed.stamp)))
        elif kind == 6:
            n = int(rng.integers(8, 30))
            args.update(names=[f"j{i}" for i in range(n)], q=np.zeros(n), dq=np.zeros(n))
        elif kind == 7:
            args["q"] = q[:5]
        tau, new = feed(**args)
        faults_seen += bool(new)
        assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= limits + 1e-12)
        assert np.max(np.abs(tau - prev)) <= MAX_STEP + 1e-9, (k, kind)
        prev = tau.copy()
        assert len(loop.fault) <= FAULT_TEXT_MAX
        if loop.fault and rng.random() < 0.2:
            loop.clear_fault()
            feed.stamp += 1_000_000
            tau, new = feed()
            assert new == "" and loop.fault == "", (k, loop.fault)
            assert np.max(np.abs(tau - prev)) <= MAX_STEP + 1e-9
            prev = tau.copy()
    assert faults_seen > 100 and loop.bad_inputs > 500
    assert loop.take_rejection_report() is not None


def test_flow_controller_hold_is_not_driven_by_an_absurd_velocity(arm):
    """Defence in depth for direct users of FlowController.hold (the loop rejects such states first)."""
    loop = _loop(arm)
    ctrl = loop.controller
    ctrl.reset_rate_limit()
    tau = ctrl.hold(Q0, np.r_[REST[:3], 1e6, REST[4:]]).copy()
    np.testing.assert_allclose(tau, _gravity(arm, Q0), atol=1e-9)
    ctrl.reset_rate_limit()
    slow = np.full(7, 0.5)
    np.testing.assert_allclose(ctrl.hold(Q0, slow), _gravity(arm, Q0) - ctrl.law.hold_damping * slow, atol=1e-9)


def test_first_command_of_a_controller_whose_driver_compensates_gravity_is_rate_limited(arm):
    """Issue 14: a restarted controller's first command jumped 3.9 Nm in 1 ms against a hardware-like
    driver. With the driver compensating gravity the arm gets nothing of ours before the first
    command, so the rate limit starts from zero."""
    loop = ControlLoop(arm, TorqueLawConfig(gravity_compensation=False), LoopConfig(idle_mode="policy"))
    params = _params(arm)
    params.x_ref = params.x_ref + np.array([0.1, 0.0, -0.1])  # far from the arm: a large first command
    assert loop.set_policy(params)
    tau, new = loop.on_joint_state(list(panda_spec.JOINT_NAMES), Q0, REST, 1, 0.0)
    assert new == ""
    assert np.all(np.abs(tau) <= MAX_STEP + 1e-9), tau
    tau, _ = loop.on_joint_state(list(panda_spec.JOINT_NAMES), Q0, REST, 2, 0.0)
    assert np.abs(tau).max() > 1.5 * MAX_STEP, "the flow does command more: the limit is what held the first one"
