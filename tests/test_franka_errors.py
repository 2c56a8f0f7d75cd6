"""libfranka errors in the Franka driver's loop: the robot lost mid-episode (franky-sim killed by its
PID) raises in readOnce; the loop aborts the episode, latches the controller's safe hold, keeps the
error text for /diagnostics and waits for a recovery instead of dying."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from franka_driver.loop import DriverConfig, reset_policy
from nf_bringup.testing.franky import FrankySim
from nf_controller_node.host import EPISODE_END
from nf_core.episode import EpisodeRun, EpisodeSpec
from nf_core.reward import RewardWeights

from franky import DriverRig

pytest.importorskip("pylibfranka")


def test_robot_lost_mid_episode_aborts_it_latches_the_hold_and_keeps_the_error(tmp_path):
    sim = FrankySim(tmp_path / "franky-sim.log")
    rig = None
    try:
        rig = DriverRig(idle_mode="hold", config=DriverConfig(reset_timeout=60.0, reset_tolerance=0.01,
                                                                reset_speed=0.02, reset_settle=20))
        start = rig.x0.copy()
        rig.driver.config.start_position = start  # already there: the reset converges at once
        params = reset_policy(start + np.array([0.0, 0.0, -0.05]), 300.0, 40.0)
        params.version = 2
        rig.loop.set_policy(params)
        rig.start()
        spec = EpisodeSpec(episode_id=9, policy_version=2, duration=30.0, decision_period=0.01,
                           control_period=0.001, sigma=None, noise_seed=0, x_goal=params.x_ref.copy(),
                           weights=RewardWeights(), chunk_decisions=10)
        rig.driver.begin_episode(0, EpisodeRun(spec)).result(timeout=120.0)
        rig.run_for(0.2)
        sim.proc.kill()  # the robot is gone (by PID)
        sim.proc.wait(10)
        deadline = time.monotonic() + 30.0
        while not rig.driver.in_error and time.monotonic() < deadline:
            time.sleep(0.05)
        d = rig.driver
        assert d.in_error and d.exceptions == 1, d.last_error
        assert "Exception" in d.last_error and "libfranka" in d.last_error, d.last_error
        assert rig.loop.fault.startswith("libfranka error"), rig.loop.fault
        ends = [e for e in rig.host.drain() if e.kind == EPISODE_END]
        assert ends and ends[-1].text.startswith("aborted: libfranka error"), ends
        assert rig.loop.episode is None
        assert rig.driver.is_alive()  # waiting for a recovery, not crashed
    finally:
        if rig is not None:
            rig.stop()
        sim.stop()


def test_robot_stalled_past_the_udp_timeout_recovers_automatically_when_asked(tmp_path):
    sim = FrankySim(tmp_path / "franky-sim.log")
    rig = None
    try:
        rig = DriverRig(idle_mode="hold", config=DriverConfig(automatic_error_recovery=True, recovery_wait=0.5))
        rig.start()
        rig.run_for(0.2)
        sim.proc.send_signal(signal.SIGSTOP)  # the robot stops sending states (by PID)
        deadline = time.monotonic() + 30.0
        while rig.driver.exceptions == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        sim.proc.send_signal(signal.SIGCONT)
        d = rig.driver
        assert d.exceptions >= 1 and "Timeout" in d.last_error, d.last_error
        assert not rig.loop.fault.startswith("libfranka")  # automatic: no latched hold
        deadline = time.monotonic() + 60.0
        while (d.sessions < 2 or d.in_error) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert d.sessions >= 2 and d.recoveries >= 1 and not d.in_error, d.last_error
        rig.run_for(0.2)  # torque control goes on
        # the new connection's clock starts again: the stamps the controller sees keep increasing
        assert rig.loop.bad_inputs == 0 and "out of order" not in rig.loop.fault, rig.loop.fault
    finally:
        if rig is not None:
            rig.stop()
        sim.proc.send_signal(signal.SIGCONT)
        sim.stop()


def test_reflex_mid_episode_aborts_it_and_automatic_recovery_goes_on(tmp_path):
    """franky-sim answers the running motion with kReflexAborted (SIGUSR1): libfranka raises its reflex
    error in the driver, the episode ends aborted, the recovery restarts torque control, and the next
    episode runs to its end."""
    sim = FrankySim(tmp_path / "franky-sim.log", reflexes=True)
    rig = None
    try:
        rig = DriverRig(idle_mode="hold", config=DriverConfig(automatic_error_recovery=True, recovery_wait=0.5,
                                                                reset_timeout=60.0, reset_tolerance=0.01,
                                                                reset_speed=0.02, reset_settle=20))
        start = rig.x0.copy()
        rig.driver.config.start_position = start
        params = reset_policy(start + np.array([0.0, 0.0, -0.03]), 300.0, 40.0)
        params.version = 2
        rig.loop.set_policy(params)
        rig.start()

        def episode(episode_id: int, duration: float) -> EpisodeRun:
            spec = EpisodeSpec(episode_id=episode_id, policy_version=2, duration=duration, decision_period=0.01,
                               control_period=0.001, sigma=None, noise_seed=0, x_goal=params.x_ref.copy(),
                               weights=RewardWeights(), chunk_decisions=10)
            return EpisodeRun(spec)

        rig.driver.begin_episode(0, episode(9, 30.0)).result(timeout=120.0)
        rig.run_for(0.2)
        line = sim.inject_reflex()
        assert "aborted" in line and "nothing" not in line, line
        d = rig.driver
        deadline = time.monotonic() + 30.0
        while d.exceptions == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert d.exceptions == 1 and "reflex" in d.last_error, d.last_error
        print(f"\n{line}\ndriver: {d.last_error}")
        ends = [e for e in rig.host.drain() if e.kind == EPISODE_END]
        assert ends and ends[-1].text.startswith("aborted: libfranka error"), ends
        deadline = time.monotonic() + 60.0
        while (d.sessions < 2 or d.in_error) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert d.sessions >= 2 and d.recoveries >= 1 and not d.in_error, d.last_error
        rig.driver.begin_episode(0, episode(10, 0.5)).result(timeout=120.0)
        deadline = time.monotonic() + 60.0
        ends = []
        while not ends and time.monotonic() < deadline:
            rig.run_for(0.1)
            ends = [e for e in rig.host.drain() if e.kind == EPISODE_END]
        assert ends and not ends[-1].text.startswith("aborted"), ends
        assert d.exceptions == 1, d.last_error
    finally:
        if rig is not None:
            rig.stop()
        sim.stop()
