"""The one driver loop (``nf_core.driver_loop``): its thread, the tick's order, the episode
hand-over; and the MuJoCo driver on it (lockstep and realtime), without ROS."""

from __future__ import annotations

import logging
import time
from concurrent.futures import Future

import numpy as np
import pytest

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.control_loop import ControlLoop, LoopConfig
from nf_controller_node.host import CHUNK, EPISODE_END, ControllerHost
from nf_core.driver_loop import DriverLoop
from nf_core.episode import EpisodeRun, EpisodeSpec
from nf_core.tick_timing import TickTiming
from sim_bridge_node.bridge import SimBridge
from sim_bridge_node.composed import SimDriverLoop
from sim_bridge_node.env import InsertionEnv


class _Host:
    """The least a host does: posted work, a constant torque, a record of the ticks."""

    def __init__(self) -> None:
        self.loop = type("Loop", (), {"episode": None})()
        self.joint_names = ["j1"]
        self.last_stamp_ns = 0
        self.tau = np.zeros(1)
        self.ticked: list[int] = []
        self.posted: list = []
        self.answer = True

    def call(self, fn) -> Future:
        future: Future = Future()
        self.posted.append((fn, future))
        return future

    def service(self) -> int:
        posted, self.posted = self.posted, []
        for fn, future in posted:
            try:
                future.set_result(fn())
            except Exception as exc:
                future.set_exception(exc)
        return len(posted)

    def tick(self, stamp_ns, q, dq, now) -> np.ndarray:
        self.ticked.append(stamp_ns)
        self.last_stamp_ns = stamp_ns
        return self.tau

    def wants_tick(self, stamp_ns: int) -> bool:
        return self.answer

    def wait_for_work(self, timeout: float) -> bool:
        time.sleep(timeout)
        return False

    def start_episode(self, run, first_stamp_ns, world_was_reset) -> None:
        self.loop.episode = run

    def set_task(self, depth: float, success: bool) -> None:
        pass

    def warm(self) -> None:
        pass


class _Counter(DriverLoop):
    """A driver whose state is a counter: reads stamp k, records what it wrote and updated."""

    def __init__(self, host: _Host, answer_every_state: bool = False) -> None:
        super().__init__(host, TickTiming(), label="test loop", answer_every_state=answer_every_state)
        self.k = 0
        self.log: list[tuple[str, int]] = []
        self.resets: list[int] = []

    def read(self):
        self.k += 1
        return self.k, np.zeros(1), np.zeros(1), time.perf_counter()

    def write(self, tau) -> None:
        self.log.append(("write", self.k))

    def update(self) -> None:
        self.log.append(("update", self.k))

    def pace(self) -> None:
        time.sleep(0.0005)

    def reset(self, seed, run, done):
        def on_loop() -> None:
            self.resets.append(seed)
            self.host.start_episode(run, self.k + 1, world_was_reset=True)
            done.set_result(None)

        return on_loop


def _wait(predicate, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.005)


def test_the_loop_thread_ticks_in_order_says_how_it_runs_and_stops():
    host = _Host()
    driver = _Counter(host)
    driver.start(logging.getLogger("test"))
    _wait(lambda: len(host.ticked) >= 20)
    driver.stop()
    assert not driver.is_alive() and driver.scheduling.startswith(("other", "fifo"))
    assert host.ticked == sorted(host.ticked) and driver.timing.ticks >= 20
    # each state: written, then the rest of the period
    writes = [k for what, k in driver.log if what == "write"]
    assert writes == host.ticked[:len(writes)]
    assert driver.log[:2] == [("write", 1), ("update", 1)]


def test_an_idle_controller_leaves_states_to_idle_unless_every_state_is_answered():
    host = _Host()
    host.answer = False
    driver = _Counter(host)
    driver.start(logging.getLogger("test"))
    _wait(lambda: driver.timing.ticks >= 10)  # idle() says go on: the tick runs without a command
    driver.stop()
    assert host.ticked == [] and not any(what == "write" for what, _ in driver.log)
    robot = _Counter(host, answer_every_state=True)  # a robot needs a command every cycle
    robot.start(logging.getLogger("test"))
    _wait(lambda: len(host.ticked) >= 10)
    robot.stop()


def test_the_episode_hand_over_runs_the_reset_on_the_loop_thread_and_a_canceled_one_not_at_all():
    host = _Host()
    driver = _Counter(host)
    run = object()
    canceled = driver.begin_episode(7, run)
    assert canceled.cancel()
    done = driver.begin_episode(8, run)
    host.service()  # the loop thread's next service
    assert done.result(timeout=1.0) is None and driver.resets == [8] and host.loop.episode is run


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")  # the loop re-raises
def test_a_reset_that_raises_fails_the_episode_and_a_loop_that_raises_says_so(caplog):
    host = _Host()
    driver = _Counter(host)

    def refuse(seed, run, done):
        def on_loop() -> None:
            raise ValueError("start refused")

        return on_loop

    driver.reset = refuse
    done = driver.begin_episode(1, object())
    host.service()
    with pytest.raises(ValueError, match="start refused"):
        done.result(timeout=1.0)

    def broken():
        raise RuntimeError("sensor gone")

    driver.read = broken
    with caplog.at_level(logging.INFO, logger="test"):
        driver.start(logging.getLogger("test"))
        _wait(lambda: not driver.is_alive())
        driver.stop()
    assert "test loop: scheduling" in caplog.text and "driver loop stopped: RuntimeError('sensor gone')" in caplog.text


def _sim(realtime: bool, idle_mode: str = "pause") -> tuple[SimDriverLoop, ControllerHost, InsertionEnv]:
    from learner_node.config import TrainConfig
    from learner_node.trainer import Trainer

    cfg = TrainConfig(task="gear")
    env = InsertionEnv("gear")
    params = Trainer(cfg).policy.to_params()
    params.version = 1
    loop = ControlLoop(ArmModel(part=env.scene.held_part), config=LoopConfig(idle_mode=idle_mode,
                                                                             max_consecutive_misses=0))
    loop.set_policy(params)
    host = ControllerHost(loop)
    return SimDriverLoop(SimBridge(env), host, realtime=realtime), host, env


@pytest.mark.parametrize("realtime", [False, True])
def test_the_sim_runs_an_episode_from_the_reset_state(realtime):
    driver, host, _ = _sim(realtime)
    params = host.loop.policy
    spec = EpisodeSpec(1, 1, 0.05, 0.01, 0.001, None, 0, params.x_ref.copy())
    run = EpisodeRun(spec)
    driver.start(logging.getLogger("test"))
    try:
        driver.begin_episode(3, run).result(timeout=30.0)
        deadline = time.monotonic() + 30.0
        events = []
        while not any(e.kind == EPISODE_END for e in events):
            assert time.monotonic() < deadline
            time.sleep(0.002)
            events += host.drain()
    finally:
        driver.stop()
    assert run.done and run.steps >= 50 and driver.bad_torques == 0
    # a chunk is stamped as its first sample (RolloutChunk.msg), the episode's first state, not as the
    # state that closed it: a bag's rollouts line up with its joint states
    chunks = [e for e in events if e.kind == CHUNK]
    end = next(e for e in events if e.kind == EPISODE_END)
    assert chunks and chunks[0].stamp_ns == host.loop.episode_start_ns > 0
    assert end.stamp_ns - chunks[0].stamp_ns >= (run.steps - 1) * 1_000_000
    assert (driver.timing is not None) == realtime
    if realtime:
        assert driver.timing.ticks >= 50 and driver.scheduling != "not started"
