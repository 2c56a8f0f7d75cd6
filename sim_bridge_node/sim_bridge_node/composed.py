"""The MuJoCo arm as the driver of a composed controller: the 1 kHz tick is a direct call. ROS-free.

``SimDriverLoop`` is the simulator's side of ``nf_core.driver_loop.DriverLoop`` (which owns the
thread, its priority, the tick's order and timing, and the episode hand-over): it reads the
simulated state, hands the controller's torque to the bridge, steps the physics, and then calls
``after_step`` (the node publishes joint states and the rest). No DDS between state and torque.

- lockstep: during episodes as fast as the physics and the controller allow; between episodes at
  most real time, and when the controller would leave a state unanswered (idle_mode "pause") the
  thread sleeps until work is posted.
- realtime: one step per ``dt`` of wall clock, like a robot's driver; the loop times itself
  (``TickTiming``): state-to-command latency, tick period, ticks that start late. It waits for each
  period with ``DeadlineWait(spin)``: asleep, then the last ``spin`` s awake without the GIL; with
  ``warm``, the controller's compiled step runs once on the last state (into scratch buffers) between
  the two, so the next tick does not start with cold caches.

Episodes (``begin_episode``) reset the world on this thread and start the episode at the reset
state, exactly as the in-process rollout does.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import Future

import numpy as np

from nf_core.driver_loop import DriverLoop, LoopHost
from nf_core.episode import EpisodeRun
from nf_core.tick_timing import LATE_AFTER, TickTiming
from sim_bridge_node.bridge import ACCEPTED, SimBridge
from sim_bridge_node.deadline_wait import DeadlineWait

_WAIT_IDLE = 0.05  # s, longest sleep of an idle lockstep loop before it looks again
TASK_EVERY = 20  # steps between task reports (depth, success) outside episodes


class SimDriverLoop(DriverLoop):
    """Steps a ``SimBridge`` with the torques of a ``LoopHost``; see the module docstring."""

    def __init__(self, bridge: SimBridge, host: LoopHost, realtime: bool,
                 after_step: Callable[[], None] = lambda: None, keep_timing: bool = False,
                 spin: float = 0.0, warm: bool = False, rt_priority: int = 0,
                 after_reset: Callable[[], None] = lambda: None) -> None:
        if tuple(host.joint_names) != tuple(bridge.joint_names):
            raise ValueError(f"controller joints {host.joint_names} differ from the simulated arm's "
                             f"{list(bridge.joint_names)}")
        super().__init__(host, TickTiming(keep_all=keep_timing) if realtime else None, rt_priority,
                         label=f"driver thread ({'realtime' if realtime else 'lockstep'})", thread_name="sim-driver")
        self.bridge = bridge
        self.realtime = realtime
        self.after_step = after_step
        self.after_reset = after_reset  # the node publishes the reset state (a bag's episode starts there)
        self._deadline = DeadlineWait(spin if realtime else 0.0)  # realtime: how the loop waits for a period
        self._warm = host.warm if warm else None  # realtime: the controller's cache warm-up before the spin
        self._success_depth = bridge.env.scene.success_depth
        # the state the tick reads: views into MuJoCo's arrays (the host copies what it keeps)
        self._state = bridge.env.state_views()
        self._dt = bridge.dt
        self._due = time.perf_counter()  # when the next tick is due (realtime: its start; lockstep: idle pace)
        self.bad_torques = 0  # torques the bridge refused (never expected: the host returns finite ones)
        self.errors: list[str] = []

    # ------------------------------------------------------------------ episodes
    def reset(self, seed: int, run: EpisodeRun, done: Future) -> Callable[[], None]:
        """On the loop thread: reset the world with ``seed`` and start ``run`` at the reset state."""

        def reset_and_start() -> None:
            self.bridge.reset(seed=seed)
            self._report_task()
            self.after_reset()
            self.host.start_episode(run, self.bridge.stamp_ns, world_was_reset=True)
            if not done.done():
                done.set_result(None)

        return reset_and_start

    def _report_task(self) -> None:
        """The task's insertion depth and success, computed once (the depth is the costly part)."""
        env = self.bridge.env
        depth = env.insertion_depth
        self.host.set_task(depth, env.task != "free" and depth >= self._success_depth)

    # ------------------------------------------------------------------ the hardware side
    def run(self, stop: threading.Event) -> None:
        """Step until ``stop`` is set (call on the driver thread)."""
        self._due = time.perf_counter()
        self.ticks(stop)

    def read(self) -> tuple[int, np.ndarray, np.ndarray, float]:
        """The simulated state (views into MuJoCo's arrays); the tick counts from now."""
        started = time.perf_counter()
        bridge = self.bridge
        stamp_ns = bridge.stamp_ns
        # an episode records the depth at its decisions' first states (and ends on one); between
        # episodes a fresh value every TASK_EVERY steps is plenty (status and diagnostics only)
        run = self.host.loop.episode
        if (run.steps % run.P == 0) if run is not None else bridge.steps % TASK_EVERY == 0:
            self._report_task()
        env = bridge.env
        q, dq = self._state or (env.q, env.dq)
        return stamp_ns, q, dq, started

    def write(self, tau: np.ndarray) -> None:
        """Realtime: the torque for the next steps; lockstep: one physics step with it."""
        bridge = self.bridge
        if self.realtime:
            ok = bridge.accept_torque(tau, time.monotonic()) == ACCEPTED
        else:
            ok = bridge.step_with(tau)
        if not ok:
            self.bad_torques += 1

    def idle(self) -> bool:
        """Lockstep waits for work instead of stepping a state nobody answers; realtime steps on."""
        if self.realtime:
            return False
        self.host.wait_for_work(_WAIT_IDLE)
        return True

    def update(self) -> None:
        """Realtime: one physics step with the last command (or the hold); then ``after_step``."""
        if self.realtime:
            self.bridge.step_realtime(time.monotonic())
        self.after_step()

    def late(self, started: float, written: float) -> bool:
        """A tick that started more than ``LATE_AFTER`` after its schedule."""
        return started - self._due > LATE_AFTER

    def pace(self) -> None:
        """Realtime: wait for the next period. Lockstep: episodes as fast as the physics allows,
        between episodes at most real time (faster would only flood the monitoring topics and take
        the CPU from the learner's update)."""
        dt = self._dt
        if not self.realtime:
            if self.host.loop.episode is not None:
                self._due = time.perf_counter()
                return
            self._due += dt
            wait = self._due - time.perf_counter()
            if wait > 0.0:
                time.sleep(wait)
            elif -wait > 10 * dt:
                self._due = time.perf_counter()
            return
        self._due += dt
        wait = self._due - time.perf_counter()
        if wait > 0.0:
            self._deadline.wait(self._due, self._warm)
        elif -wait > 10 * dt:  # far behind (a stall): start a new schedule instead of racing
            self.timing.resyncs += 1
            self._due = time.perf_counter()
