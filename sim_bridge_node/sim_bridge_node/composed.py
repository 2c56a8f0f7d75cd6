"""The MuJoCo arm as the driver of a composed controller: the 1 kHz tick is a direct call. ROS-free.

``SimDriverLoop`` runs on its own thread in the process that also holds the ``nf_controller``
node. Each step: posted work (``ControllerHost.service``), the state, the controller's torque
(``ControllerHost.tick``), one physics step with it, then ``after_step`` (the node publishes
joint states and the rest). No DDS between state and torque.

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

import array
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future

import numpy as np

from nf_controller_node.host import ControllerHost
from nf_core.episode import EpisodeRun
from nf_core.tick_timing import LATE_AFTER, TickTiming
from sim_bridge_node.bridge import ACCEPTED, SimBridge
from sim_bridge_node.deadline_wait import DeadlineWait

_WAIT_IDLE = 0.05  # s, longest sleep of an idle lockstep loop before it looks again
TASK_EVERY = 20  # steps between task reports (depth, success) outside episodes


class SimDriverLoop:
    """Steps a ``SimBridge`` with the torques of a ``ControllerHost``; see the module docstring."""

    def __init__(self, bridge: SimBridge, host: ControllerHost, realtime: bool,
                 after_step: Callable[[], None] = lambda: None, keep_timing: bool = False,
                 spin: float = 0.0, warm: bool = False) -> None:
        if tuple(host.joint_names) != tuple(bridge.joint_names):
            raise ValueError(f"controller joints {host.joint_names} differ from the simulated arm's "
                             f"{list(bridge.joint_names)}")
        self.bridge = bridge
        self.host = host
        self.realtime = realtime
        self.after_step = after_step
        self.timing = TickTiming(keep_all=keep_timing) if realtime else None
        self._deadline = DeadlineWait(spin if realtime else 0.0)  # realtime: how the loop waits for a period
        self._warm = host.warm if warm else None  # realtime: the controller's cache warm-up before the spin
        self._success_depth = bridge.env.scene.success_depth
        # the state the tick reads: views into MuJoCo's arrays (the host copies what it keeps)
        self._state = bridge.env.state_views()
        self.bad_torques = 0  # torques the bridge refused (never expected: the host returns finite ones)
        self.errors: list[str] = []

    # ------------------------------------------------------------------ episodes (any thread)
    def begin_episode(self, seed: int, run: EpisodeRun) -> Future:
        """Reset the world with ``seed`` and start ``run`` at the reset state, on the loop's thread."""

        def reset_and_start() -> None:
            self.bridge.reset(seed=seed)
            self._report_task()
            self.host.start_episode(run, self.bridge.stamp_ns, world_was_reset=True)

        return self.host.call(reset_and_start)

    # ------------------------------------------------------------------ the loop
    def run(self, stop: threading.Event) -> None:
        """Step until ``stop`` is set (call on the driver thread)."""
        if self.realtime:
            self._run_realtime(stop)
        else:
            self._run_lockstep(stop)

    def _report_task(self) -> None:
        """The task's insertion depth and success, computed once (the depth is the costly part)."""
        env = self.bridge.env
        depth = env.insertion_depth
        self.host.set_task(depth, env.task != "free" and depth >= self._success_depth)

    def _tick(self, stamp_ns: int, now: float) -> np.ndarray:
        bridge, host = self.bridge, self.host
        env = bridge.env
        # an episode records the depth at its decisions' first states (and ends on one); between
        # episodes a fresh value every TASK_EVERY steps is plenty (status and diagnostics only)
        run = host.loop.episode
        if (run.steps % run.P == 0) if run is not None else bridge.steps % TASK_EVERY == 0:
            self._report_task()
        q, dq = self._state or (env.q, env.dq)
        return host.tick(stamp_ns, q, dq, now)

    def _run_lockstep(self, stop: threading.Event) -> None:
        bridge, host = self.bridge, self.host
        dt = bridge.dt
        due = time.perf_counter()
        while not stop.is_set():
            host.service()
            stamp_ns = bridge.stamp_ns
            if not host.wants_tick(stamp_ns):
                host.wait_for_work(_WAIT_IDLE)
                continue
            if not bridge.step_with(self._tick(stamp_ns, time.monotonic())):
                self.bad_torques += 1
            self.after_step()
            if host.loop.episode is not None:
                due = time.perf_counter()  # episodes: as fast as the physics allows
                continue
            # between episodes (idle_mode hold or policy) at most real time: faster would only
            # flood the monitoring topics and take the CPU from the learner's update
            due += dt
            wait = due - time.perf_counter()
            if wait > 0.0:
                time.sleep(wait)
            elif -wait > 10 * dt:
                due = time.perf_counter()

    def _run_realtime(self, stop: threading.Event) -> None:
        bridge, host, timing = self.bridge, self.host, self.timing
        dt = bridge.dt
        due = time.perf_counter()
        while not stop.is_set():
            host.service()
            started = time.perf_counter()
            stamp_ns = bridge.stamp_ns
            if host.wants_tick(stamp_ns):
                now = time.monotonic()
                if bridge.accept_torque(self._tick(stamp_ns, now), now) != ACCEPTED:
                    self.bad_torques += 1
            written = time.perf_counter()
            bridge.step_realtime(time.monotonic())
            timing.tick(started, written - started, late=started - due > LATE_AFTER)
            self.after_step()
            due += dt
            wait = due - time.perf_counter()
            if wait > 0.0:
                self._deadline.wait(due, self._warm)
            elif -wait > 10 * dt:  # far behind (a stall): start a new schedule instead of racing
                timing.resyncs += 1
                due = time.perf_counter()


def latencies_us(values: array.array | list[float]) -> dict[str, float]:
    """p50/p99/p99.9/max of latencies given in s, in microseconds."""
    a = np.frombuffer(values, dtype=np.float64) if isinstance(values, array.array) else np.asarray(values)
    if a.size == 0:
        return {"count": 0, "p50_us": 0.0, "p99_us": 0.0, "p999_us": 0.0, "max_us": 0.0}
    p50, p99, p999 = np.percentile(a, [50, 99, 99.9]) * 1e6
    return {"count": int(a.size), "p50_us": float(p50), "p99_us": float(p99), "p999_us": float(p999),
            "max_us": float(a.max() * 1e6)}
