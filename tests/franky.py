"""The ROS-free driver stack of a test, built around a connection to the franky-sim rig
(``nf_bringup.testing.franky``)."""

from __future__ import annotations

import gc
import logging
import time

import numpy as np

from franka_driver.loop import DriverConfig, FrankaDriverLoop
from franka_driver.robot_model import ArmSpec, identify
from nf_bringup.testing.franky import HOST
from nf_controller_node.control_loop import ControlLoop, LoopConfig
from nf_controller_node.host import ControllerHost
from nf_controller_node.torque_law import TorqueLawConfig
from nf_core import panda_spec
from nf_core.driver_loop import loop_priority
from nf_core.thread_priority import AUTO, open_robot


class DriverRig:
    """pylibfranka connected to the simulator, the arm identified, a ControlLoop (gravity
    compensation off, as on a Franka) behind a ControllerHost, and a FrankaDriverLoop on a thread.

    ``spec``: the arm description the controller uses instead of the identified one (to measure a
    wrong description, which the driver itself refuses); ``identification`` is still the robot's.
    ``law``: the controller's torque law (default: the law's defaults, gravity compensation off)."""

    def __init__(self, idle_mode: str = "hold", config: DriverConfig | None = None,
                 spec: ArmSpec | None = None, law: TorqueLawConfig | None = None) -> None:
        import pylibfranka as franka

        if law is not None and law.gravity_compensation:
            raise ValueError("the robot adds gravity itself: the law's gravity_compensation must be off")
        self.franka = franka
        def connect() -> object:  # this thread keeps its scheduling (libfranka's Robot() sets FIFO 99)
            return open_robot(lambda: franka.Robot(HOST, franka.RealtimeConfig.kIgnore))

        robot = connect()
        state = robot.read_once()
        self.identification = identify("auto", state, robot.load_model())
        self.spec = spec = spec or self.identification.spec
        self.arm = spec.arm_model(panda_spec.GEAR_PART)
        self.loop = ControlLoop(self.arm, law or TorqueLawConfig(gravity_compensation=False),
                                LoopConfig(idle_mode=idle_mode, max_consecutive_misses=0),
                                joint_names=spec.joint_names)
        spec.fit_loop(self.loop)  # as nf_franka_stack does
        self.host = ControllerHost(self.loop)
        self.tcp_arm = spec.arm_model(panda_spec.GEAR_PART)
        self.x0 = self.tcp_arm.tcp_position(np.asarray(state.q))
        self.q = np.asarray(state.q, dtype=float).copy()  # joint positions of the last state
        self._ticks: list[tuple[np.ndarray, np.ndarray]] = []  # (torque, torque limits), one append per tick
        self.dq_max = np.zeros(7)  # rad/s, each joint's fastest speed since it was last zeroed
        errors = (franka.FrankaException, franka.ControlException, franka.CommandException,
                  franka.NetworkException, franka.RealtimeException, franka.InvalidOperationException)
        self.driver = FrankaDriverLoop(robot, self.host, self.tcp_arm.tcp_position, config or DriverConfig(),
                                       franka.Torques, errors, after_tick=self._record,
                                       connect=connect,  # scheduled as the driver node's with realtime: ignore
                                       rt_priority=loop_priority(AUTO, False, "the torque loop"))
        del robot  # the loop owns the connection

    def _record(self, q: np.ndarray, dq: np.ndarray, tau: np.ndarray, stamp_ns: int) -> None:
        self.q = q
        np.maximum(self.dq_max, np.abs(dq), out=self.dq_max)
        self._ticks.append((tau.copy(), self.loop.controller.law.torque_limits.copy()))

    def torques_and_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Every tick's torque and the limits in force, as (ticks, 7) arrays of one length: read while
        the loop thread may still append (two separate lists could differ by the tick in between)."""
        ticks = list(self._ticks)
        return np.array([t for t, _ in ticks]), np.array([lim for _, lim in ticks])

    def start(self) -> None:
        """The loop on its own thread, scheduled as the driver node's with ``realtime: ignore``."""
        self.driver.start(logging.getLogger("franka-rig"))

    def robot_seconds(self) -> float:
        """Robot time of the last state (s)."""
        return self.host.last_stamp_ns * 1e-9

    def run_for(self, robot_seconds: float, timeout: float = 120.0) -> None:
        """Wait until the robot's clock advanced by ``robot_seconds`` (the simulator may run slower
        than real time on a busy machine)."""
        deadline = time.monotonic() + timeout
        while self.host.last_stamp_ns == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        end = self.robot_seconds() + robot_seconds
        while self.robot_seconds() < end:
            if time.monotonic() > deadline or not self.driver.is_alive():
                raise TimeoutError(f"robot clock at {self.robot_seconds():.3f} s, waited for {end:.3f} s")
            time.sleep(0.01)

    def stop(self) -> None:
        """Stop the loop and disconnect (the simulator serves one client at a time)."""
        self.driver.stop(10.0)
        self.driver.robot = None
        gc.collect()
