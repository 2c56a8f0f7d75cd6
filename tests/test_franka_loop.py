"""The Franka driver's loop logic against a scripted stand-in for pylibfranka (no simulator, no
network): a libfranka exception mid-episode, recovery by a person or automatically (with an
episode asked for during the error), a policy whose x_ref is not the configured goal."""

from __future__ import annotations

import logging
import re
import time

import numpy as np
import pytest

from franka_driver.loop import DriverConfig, FrankaDriverLoop, reset_policy
from franka_driver.robot_model import FR3
from nf_controller_node.control_loop import ControlLoop, LoopConfig
from nf_controller_node.host import EPISODE_END, ControllerHost
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import panda_spec
from nf_core.episode import EpisodeRun, EpisodeSpec
from nf_core.reward import RewardWeights

Q0 = np.array([0.0, 0.0, 0.0, -1.57, 0.0, 1.57, 0.785])


class ReflexError(RuntimeError):
    """Stands in for pylibfranka.ControlException."""


class _Duration:
    def __init__(self, s: float) -> None:
        self.s = s

    def to_sec(self) -> float:
        return self.s


class _State:
    def __init__(self, q: np.ndarray, dq: np.ndarray, t: float) -> None:
        self.q, self.dq, self.time = q.tolist(), dq.tolist(), _Duration(t)
        self.last_motion_errors = "[joint_reflex]"


class _Torques:
    def __init__(self, tau: list[float]) -> None:
        self.tau_J = tau
        self.motion_finished = False


class FakeRobot:
    """1 kHz robot time, joints that stay put (heavy, damped); raises ``ReflexError`` at tick ``fail_at``."""

    def __init__(self, fail_at: int = -1) -> None:
        self.q, self.dq, self.t = Q0.copy(), np.zeros(7), 0.0
        self.ticks = 0
        self.fail_at = fail_at
        self.recoveries = 0
        self.sessions = 0

    def start_torque_control(self) -> FakeRobot:
        self.sessions += 1
        return self

    def readOnce(self) -> tuple[_State, _Duration]:
        time.sleep(0.0002)
        self.ticks += 1
        self.t += 0.001
        if self.ticks == self.fail_at:
            raise ReflexError("libfranka: Move command aborted: motion aborted by reflex! [\"cartesian_reflex\"]")
        return _State(self.q, self.dq, self.t), _Duration(0.001)

    def writeOnce(self, torques: _Torques) -> None:
        self.dq = 0.9 * self.dq + 1e-4 * np.asarray(torques.tau_J)
        self.q = self.q + 0.001 * self.dq

    def read_once(self) -> _State:
        return _State(self.q, self.dq, self.t)

    def automatic_error_recovery(self) -> None:
        self.recoveries += 1


def _rig(robot: FakeRobot, **config: object) -> tuple[FrankaDriverLoop, ControlLoop, ControllerHost]:
    arm = FR3.arm_model(panda_spec.GEAR_PART)
    loop = ControlLoop(arm, TorqueLawConfig(gravity_compensation=False), LoopConfig(idle_mode="hold"),
                       joint_names=FR3.joint_names)
    FR3.fit_loop(loop)
    host = ControllerHost(loop)
    tcp = FR3.arm_model(panda_spec.GEAR_PART).tcp_position
    x0 = tcp(Q0)
    cfg = DriverConfig(start_position=x0, reset_tolerance=0.01, reset_speed=1.0, reset_settle=5, **config)
    params = reset_policy(x0, 300.0, 40.0)
    params.version = 1
    loop.set_policy(params)
    return FrankaDriverLoop(robot, host, tcp, cfg, _Torques, (ReflexError,)), loop, host


def _episode(x_goal: np.ndarray, seconds: float = 5.0) -> EpisodeRun:
    spec = EpisodeSpec(episode_id=5, policy_version=1, duration=seconds, decision_period=0.01, control_period=0.001,
                       sigma=None, noise_seed=0, x_goal=x_goal, weights=RewardWeights(), chunk_decisions=10)
    return EpisodeRun(spec)


def _wait(predicate: object, timeout: float = 20.0) -> bool:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def test_reflex_mid_episode_aborts_it_latches_the_hold_and_waits_for_a_person():
    robot = FakeRobot(fail_at=400)
    driver, loop, host = _rig(robot)
    driver.start(logging.getLogger("franka-loop"))
    try:
        driver.begin_episode(0, _episode(loop.policy.x_ref)).result(timeout=20)
        assert _wait(lambda: driver.in_error)
        assert "ReflexError" in driver.last_error and "joint_reflex" in driver.last_error
        assert loop.fault.startswith("libfranka error")
        ends = [e for e in host.drain() if e.kind == EPISODE_END]
        assert ends and ends[0].text.startswith("aborted: libfranka error")
        with pytest.raises(RuntimeError, match="libfranka error"):  # no episode while the error stands
            driver.begin_episode(0, _episode(loop.policy.x_ref)).result(timeout=20)
        time.sleep(0.3)
        assert robot.recoveries == 0 and robot.sessions == 1  # nobody asked: no recovery
        driver.request_recovery()
        assert _wait(lambda: robot.sessions == 2)
        assert robot.recoveries == 1 and not driver.in_error
        assert loop.fault.startswith("libfranka error")  # the controller holds until clear_fault
        host.call(loop.clear_fault).result(timeout=5)
        driver.begin_episode(0, _episode(loop.policy.x_ref)).result(timeout=20)
    finally:
        driver.stop()


def test_automatic_recovery_goes_on_and_an_episode_asked_meanwhile_starts_after_it():
    robot = FakeRobot(fail_at=50)
    driver, loop, _host = _rig(robot, automatic_error_recovery=True, recovery_wait=0.3)
    driver.start(logging.getLogger("franka-loop"))
    try:
        assert _wait(lambda: driver.in_error)
        assert not loop.fault  # automatic: no latch
        started = driver.begin_episode(0, _episode(loop.policy.x_ref, seconds=0.05))
        started.result(timeout=20)  # waited for the recovery, then reset and started
        assert robot.recoveries == 1 and robot.sessions == 2 and driver.resets_done == 1
    finally:
        driver.stop()


def test_an_episode_whose_policy_is_not_the_goal_is_refused():
    robot = FakeRobot()
    driver, loop, _host = _rig(robot, goal=np.array([0.4, 0.1, 0.2]))
    driver.start(logging.getLogger("franka-loop"))
    try:
        with pytest.raises(RuntimeError, match="is not the goal parameter"):
            driver.begin_episode(0, _episode(loop.policy.x_ref)).result(timeout=20)
        assert loop.episode is None and driver.resets_done == 0
    finally:
        driver.stop()


def test_reset_motions_return_to_the_first_resets_posture():
    """Issue 30: the first reset records where it reached the start; every later reset pulls the
    joints back there (a joint spring in the controller only while the reset runs)."""
    robot = FakeRobot()
    driver, loop, _host = _rig(robot)
    assert driver.posture is None
    driver.start(logging.getLogger("franka-loop"))
    try:
        driver.begin_episode(0, _episode(loop.policy.x_ref, seconds=0.05)).result(timeout=20)
        assert driver.resets_done == 1 and driver.posture is not None
        np.testing.assert_allclose(driver.posture, Q0, atol=1e-3)  # the fake arm barely moves
        assert loop.controller.posture is None, "the episode runs without the posture spring"
        assert _wait(lambda: loop.episode is None)
        seen = []
        done = driver.begin_episode(0, _episode(loop.policy.x_ref, seconds=0.05))
        while not done.done():
            seen.append(loop.controller.posture)
            time.sleep(0.0005)
        done.result(timeout=20)
        during = [p for p in seen if p is not None]
        assert during, "the second reset ran with the posture spring"
        np.testing.assert_allclose(during[0][0], driver.posture)
        assert during[0][1:] == (DriverConfig.reset_posture_stiffness, DriverConfig.reset_posture_damping)
        assert loop.controller.posture is None and "rad off" in driver.last_reset
    finally:
        driver.stop()
    with pytest.raises(ValueError, match="reset_posture must be 7"):
        _rig(FakeRobot(), reset_posture=Q0[:5])


def test_a_restarted_session_anchors_the_hold_where_the_arm_is_now():
    """Issue 14: the safe hold brakes to its anchor. After a reflex the arm may have been moved (by
    the reflex, by a person) before torque control restarts: the new session's hold must anchor at
    the arm's position then, not pull it back to where the old session's hold began."""
    robot = FakeRobot(fail_at=100)
    driver, loop, host = _rig(robot)
    ctrl = loop.controller
    driver.start(logging.getLogger("franka-loop"))
    try:
        assert _wait(lambda: driver.in_error)
        before = host.call(lambda: ctrl.hold_anchor).result(timeout=5)
        assert before is not None and np.allclose(before, Q0, atol=1e-3)  # the idle hold began at Q0
        moved = Q0 + np.array([0.1, -0.05, 0.08, 0.05, -0.1, 0.05, 0.15])
        robot.q = moved.copy()  # the driver waits for a recovery: nobody else touches the robot now
        driver.request_recovery()
        assert _wait(lambda: robot.sessions == 2 and robot.ticks > 150)
        after = host.call(lambda: ctrl.hold_anchor).result(timeout=5)
        np.testing.assert_allclose(after, moved, atol=1e-9)
        assert loop.fault.startswith("libfranka error")  # still held until clear_fault
    finally:
        driver.stop()


def test_fit_loop_gives_the_loop_the_fr3s_ranges_instead_of_the_pandas():
    """A ControlLoop defaults to the Panda's plausibility ranges: fr3_joint6 may reach 4.52 rad, the
    Panda's joint 6 only 3.75; after ``fit_loop`` a state the FR3 can be in is accepted and one beyond
    its range (+ the margin) is not, and the torque limits are the smaller of both."""
    loop = ControlLoop(FR3.arm_model(panda_spec.GEAR_PART), TorqueLawConfig(gravity_compensation=False),
                       LoopConfig(idle_mode="hold"), joint_names=FR3.joint_names)
    q = Q0.copy()
    q[5] = 4.3  # inside the FR3's range, beyond the Panda's
    _, fault = loop.on_joint_state(FR3.joint_names, q, np.zeros(7), 1, 0.0)
    assert "implausible" in fault
    loop = ControlLoop(FR3.arm_model(panda_spec.GEAR_PART), TorqueLawConfig(gravity_compensation=False),
                       LoopConfig(idle_mode="hold"), joint_names=FR3.joint_names)
    FR3.fit_loop(loop)
    margin = panda_spec.Q_PLAUSIBLE_MARGIN
    assert np.allclose(loop.q_max, FR3.q_max + margin) and np.allclose(loop.q_min, FR3.q_min - margin)
    tau, fault = loop.on_joint_state(FR3.joint_names, q, np.zeros(7), 1, 0.0)
    assert fault == "" and np.all(np.isfinite(tau))
    q[5] = FR3.q_max[5] + margin + 0.01
    _, fault = loop.on_joint_state(FR3.joint_names, q, np.zeros(7), 2, 0.001)
    assert "implausible" in fault
    law = loop.controller.law
    assert np.all(law.torque_limits <= FR3.torque_limits)


class HandRobot(FakeRobot):
    """A FakeRobot moved by a hand: while ``hand_dq`` is set the joints move at it whatever the command
    (until tick ``hand_until``, then the hand holds them still); keeps every command."""

    def __init__(self) -> None:
        super().__init__()
        self.hand_dq: np.ndarray | None = None
        self.hand_until = 1 << 62
        self.commands: list[np.ndarray] = []

    def writeOnce(self, torques: _Torques) -> None:
        self.commands.append(np.asarray(torques.tau_J, dtype=float))
        if self.hand_dq is None:
            super().writeOnce(torques)
        else:
            self.dq = self.hand_dq.copy() if self.ticks < self.hand_until else np.zeros(7)
            self.q = self.q + 0.001 * self.dq


def test_hand_guiding_commands_zero_torque_then_the_hold_takes_over_from_zero_where_the_hand_left_the_arm():
    robot = HandRobot()
    driver, loop, host = _rig(robot, guide=True)
    ctrl = loop.controller
    driver.start(logging.getLogger("franka-loop"))
    try:
        x_ref = loop.policy.x_ref + np.array([0.05, 0.0, 0.0])  # a pull of 15 N: the episode's law is not zero
        run = _episode(x_ref, seconds=0.6)
        robot.hand_until = robot.ticks + 1_000_000  # moves until told where to stop
        robot.hand_dq = np.array([0.0, 0.2, 0.0, 0.1, 0.0, 0.0, 0.0])  # a person moves the arm ...
        driver.begin_episode(0, run).result(timeout=20)
        first = len(robot.commands)
        robot.hand_until = robot.ticks + 300  # ... for 0.3 s of robot time, then holds it still
        assert _wait(lambda: loop.episode is None)
        ends = [e for e in host.drain() if e.kind == EPISODE_END]
        assert ends and ends[-1].text == "", "a guided episode that stays within the limits completes"
        left_at = robot.q.copy()
        robot.hand_dq = None  # let go
        assert _wait(lambda: len(robot.commands) > first + 900)
        anchor = host.call(lambda: ctrl.hold_anchor).result(timeout=5)
    finally:
        driver.stop()
    cmds = np.array(robot.commands[:-1])  # the last: the stop's motion-finished zero
    steps = np.abs(np.diff(cmds, axis=0)).max(axis=1)
    assert steps.max() <= 1.0 + 1e-9, "no command steps by more than the 1 Nm per ms rate limit"
    guided = cmds[first + 50 : first + 550]
    assert np.abs(guided).max() == 0.0, "zero torque while guided (the robot adds gravity)"
    assert driver.guides == 1 and driver.guide_stops == 0
    np.testing.assert_allclose(anchor, left_at, atol=2e-3)  # held where the hand left it, not where it began
    assert np.abs(anchor - Q0).max() > 0.02


@pytest.mark.parametrize("case", ["speed", "limit", "time"])
def test_hand_guiding_stops_into_the_hold_on_a_fast_joint_a_joint_limit_or_its_time(case):
    robot = HandRobot()
    extra = {"guide_timeout": 0.2} if case == "time" else {}
    driver, loop, host = _rig(robot, guide=True, **extra)
    driver.start(logging.getLogger("franka-loop"))
    try:
        driver.begin_episode(0, _episode(loop.policy.x_ref, seconds=2.0)).result(timeout=20)
        if case == "speed":
            robot.hand_dq = np.array([0.0, 0.0, 1.3, 0.0, 0.0, 0.0, 0.0])
        elif case == "limit":  # joint 4 towards its upper limit (-0.0698 on the FR3), 0.5 rad/s
            robot.hand_dq = np.array([0.0, 0.0, 0.0, 0.5, 0.0, 0.0, 0.0])
            robot.q[3] = FR3.q_max[3] - 0.15
        assert _wait(lambda: loop.episode is None, timeout=5)
        stopped_at = robot.q.copy()
        ends = [e for e in host.drain() if e.kind == EPISODE_END]
        robot.hand_dq = np.zeros(7) if case != "time" else None
    finally:
        driver.stop()
    want = {"speed": "joint 3 at 1.30 rad/s", "limit": "joint 4 at", "time": "guided for"}[case]
    assert ends and ends[-1].text.startswith("aborted: hand-guiding stopped: ") and want in ends[-1].text
    assert driver.guide_stops == 1 and want in driver.last_guide_stop
    if case == "limit":  # stopped on the first state inside the margin (0.5 mrad per state at 0.5 rad/s)
        room = float(re.search(r"([\d.]+) rad from its limit", driver.last_guide_stop).group(1))
        assert DriverConfig.guide_limit_margin - 0.001 <= room <= DriverConfig.guide_limit_margin  # 3 decimals
        assert FR3.q_max[3] - stopped_at[3] > 0.0, "the hand moved it on, but not past the limit"
    cmds = np.array(robot.commands[:-1])  # the last: the stop's motion-finished zero
    assert np.abs(np.diff(cmds, axis=0)).max() <= 1.0 + 1e-9


def test_reset_via_points_are_checked():
    with pytest.raises(ValueError, match="reset_via must be"):
        DriverConfig(reset_via=np.zeros((2, 2))).check()
    with pytest.raises(ValueError, match="reset_via must be"):
        DriverConfig(reset_via=np.array([[0.5, 0.0, np.nan]])).check()
    from franka_driver.node import via_points

    assert via_points([0.0]) is None and via_points([]) is None
    np.testing.assert_allclose(via_points([0.5, 0, 0.35, 0.7, 0, 0.35]), [[0.5, 0, 0.35], [0.7, 0, 0.35]])
    with pytest.raises(ValueError, match="multiple of 3"):
        via_points([0.5, 0.0, 0.35, 0.7])


class WatchingRobot(FakeRobot):
    """A FakeRobot that notes, at every command, the force bound of the evaluator the controller ran."""

    def __init__(self) -> None:
        super().__init__()
        self.controller = None
        self.bounds: list[float] = []

    def writeOnce(self, torques: _Torques) -> None:
        if self.controller is not None:
            self.bounds.append(self.controller.evaluator.force_bound)
        super().writeOnce(torques)


def test_the_reset_pulls_at_most_its_own_bound_whatever_the_policys_law():
    """A policy without a force bound (its law's 0) must not make the reset motion pull with its full spring."""
    robot = WatchingRobot()
    driver, loop, _host = _rig(robot, reset_force_bound=25.0)
    assert loop.controller.law.potential_force_bound == 0.0
    robot.controller = loop.controller
    driver.start(logging.getLogger("franka-loop"))
    try:
        driver.begin_episode(0, _episode(loop.policy.x_ref, seconds=0.05)).result(timeout=20)
        assert _wait(lambda: loop.episode is None)
    finally:
        driver.stop()
    bounds = np.array(robot.bounds)
    assert (bounds == 25.0).sum() >= 5, "the reset (5 settling ticks in the rig) ran with its own bound"
    assert bounds[-1] == 0.0, "the episode's policy runs with its law's bound"
