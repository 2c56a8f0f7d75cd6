"""ROS-free core of ``sim_bridge_node``: command checks, driver-side gravity, command timeout and
safe hold, and a simulation clock that never runs backwards.

The node only moves messages in and out; everything it decides is here, so it is tested
without a ROS graph. Two ways to drive it:

- lockstep: ``accept_command`` then ``step_commanded`` (one physics step per accepted command);
- realtime: ``accept_command`` whenever a command arrives, ``step_realtime(now)`` every tick,
  which applies the last command until it is older than ``command_timeout`` and the safe hold
  (the simulator's gravity torque + joint damping + a ``hold_stiffness`` spring to where the hold
  began, as a robot brakes where its commands stopped) after that.

A bad command costs less than a good one: it is counted and its reason kept (bounded to
``ERROR_TEXT_MAX``); the node logs ``take_error_report()`` from its diagnostics timer, never per
message.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from sim_bridge_node.env import InsertionEnv, Observation, copy_if_finite

MODES = ("lockstep", "realtime")
ACCEPTED, STALE, BAD = "accepted", "stale", "bad"  # outcomes of accept_command
ERROR_TEXT_MAX = 300  # characters of a bad command's reason kept in last_error


@dataclass(frozen=True)
class BridgeConfig:
    """Settings of the bridge; ``check`` names the first bad value."""

    mode: str = "lockstep"  # lockstep | realtime
    command_timeout: float = 0.05  # s of wall time without a command before the safe hold (realtime)
    driver_gravity_compensation: bool = False  # add the simulator's gravity torque to every command (Franka)
    hold_damping: float = 2.0  # Nm s/rad (N s/m for the block), joint damping of the safe hold
    hold_stiffness: float = 0.0  # Nm/rad (N/m), safe hold's spring to where it began (0: damping only)

    def check(self) -> None:
        """Raise ``ValueError`` with the reason if a value is out of range."""
        if self.mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {self.mode!r}")
        if not np.isfinite(self.command_timeout) or self.command_timeout <= 0.0:
            raise ValueError(f"command_timeout must be > 0 s, got {self.command_timeout}")
        if not np.isfinite(self.hold_damping) or self.hold_damping < 0.0:
            raise ValueError(f"hold_damping must be >= 0, got {self.hold_damping}")
        if not np.isfinite(self.hold_stiffness) or self.hold_stiffness < 0.0:
            raise ValueError(f"hold_stiffness must be >= 0, got {self.hold_stiffness}")


class SimBridge:
    """Steps an ``InsertionEnv`` with checked commands; counts everything that went wrong."""

    def __init__(self, env: InsertionEnv, config: BridgeConfig | None = None) -> None:
        self.env = env
        self.config = config or BridgeConfig()
        self.config.check()
        m = env.model
        self._vadr = np.array([m.joint(n).dofadr[0] for n in env.scene.joint_names])
        self._scratch = mujoco.MjData(m)  # for the gravity torque, so the real state is untouched
        self._rne = np.zeros(m.nv)
        self._command = np.zeros(env.nu)  # last accepted command, without the driver's gravity
        self._has_command = False
        self._command_time = -np.inf  # wall time (s) of the last accepted command
        self._command_sim_time = 0.0  # sim time (s) when the last command was accepted
        self.hold_delay = float("nan")  # sim s the last command was applied before the latest timeout hold
        self._hold_anchor: np.ndarray | None = None  # q where the current safe hold began
        self.torque = np.zeros(env.nu)  # torque applied in the last step (Nm), gravity included
        # what ``effort`` reports: the applied torque, less the gravity the driver added on its own with
        # driver_gravity_compensation (as Franka's driver reports it), so a controller that seeds its rate
        # limit from effort starts from its own command's part
        self.effort = np.zeros(env.nu)
        self.clock_offset = 0.0  # sim time (s) of all earlier episodes: the clock never goes back
        self.steps = 0
        self.bad_commands = 0
        self.stale_commands = 0  # lockstep: replies to an earlier state (late, or duplicated by a resend)
        self.command_timeouts = 0  # times the realtime bridge fell into the safe hold for lack of commands
        self.hold_steps = 0
        self.in_hold = True  # realtime: no command yet
        self._error: tuple = ()  # why the latest bad command was ignored, formatted only when read
        self._bad_reported = 0  # bad_commands at the last take_error_report

    # ------------------------------------------------------------------ state
    @property
    def joint_names(self) -> tuple[str, ...]:
        """Names of the commanded joints, in command order."""
        return tuple(self.env.scene.joint_names)

    @property
    def sim_time(self) -> float:
        """Simulated time since the bridge started, across resets (s); stamps and /clock use it."""
        return self.clock_offset + self.env.time

    @property
    def stamp_ns(self) -> int:
        """Stamp of the current state (ns of simulated time): what joint_states and clock carry."""
        return round((self.clock_offset + self.env.data.time) * 1e9)  # sim_time, without two property calls

    @property
    def dt(self) -> float:
        """Physics step (s)."""
        return float(self.env.model.opt.timestep)

    def gravity(self) -> np.ndarray:
        """Gravity torque of the simulated arm at its current configuration (Nm), no velocity terms."""
        m, d = self.env.model, self._scratch
        d.qpos[:] = self.env.data.qpos
        d.qvel[:] = 0.0
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        mujoco.mj_comVel(m, d)
        mujoco.mj_rne(m, d, 0, self._rne)
        return self._rne[self._vadr].copy()

    def hold_torque(self, gravity: np.ndarray | None = None) -> np.ndarray:
        """Safe hold of the driver: gravity compensation + joint damping + a joint spring
        (``hold_stiffness``) to the position where this hold began (its anchor). ``gravity``: this
        state's gravity torque, if the caller has it already."""
        cfg, env = self.config, self.env
        tau = (self.gravity() if gravity is None else gravity) - cfg.hold_damping * env.dq
        if cfg.hold_stiffness > 0.0:
            q = env.q
            if self._hold_anchor is None:
                self._hold_anchor = q
            tau -= cfg.hold_stiffness * (q - self._hold_anchor)
        return tau

    # ------------------------------------------------------------------ commands
    def _checked(self, data: Sequence[float]) -> np.ndarray | tuple:
        """The command as an array, or why not as data (kind, value): no string work and no
        exception on the path a flood of bad commands takes."""
        n = self.env.nu
        try:
            if len(data) != n:  # before converting a possibly huge message
                return ("size", len(data))
            arr = np.asarray(data, dtype=np.float64).reshape(-1)
        except (TypeError, ValueError) as exc:
            return ("type", exc)
        if arr.size != n:
            return ("size", arr.size)
        if not np.isfinite(arr).all():
            return ("finite", arr)  # no copy: a message's data is not reused after its callback
        return arr

    def _error_text(self, error: tuple) -> str:
        kind, value = error
        if kind == "size":
            return f"command has {value} values, expected {self.env.nu} ({', '.join(self.joint_names)})"
        if kind == "finite":
            names = [self.joint_names[i] for i in np.flatnonzero(~np.isfinite(value))]
            return f"command contains NaN/Inf for {names}"
        return f"command is not an array of numbers: {value}"

    @property
    def last_error(self) -> str:
        """Why the latest bad command was ignored ("" if none was), at most ``ERROR_TEXT_MAX`` characters."""
        if not self._error:
            return ""
        text = self._error_text(self._error)
        if len(text) > ERROR_TEXT_MAX:
            text = text[: ERROR_TEXT_MAX - 30] + f"... [+{len(text) - ERROR_TEXT_MAX + 30} chars]"
        return text

    def check_command(self, data: Sequence[float]) -> np.ndarray:
        """The command as an array, or ``ValueError`` naming what is wrong with it."""
        arr = self._checked(data)
        if isinstance(arr, tuple):
            raise ValueError(self._error_text(arr))
        return arr

    def take_error_report(self) -> str | None:
        """One bounded line about the bad commands ignored since the last call (None if none): for
        the node to log from its diagnostics timer instead of per message."""
        n = self.bad_commands - self._bad_reported
        if n == 0:
            return None
        self._bad_reported = self.bad_commands
        return f"{n} bad effort command(s) ignored ({self.bad_commands} in all), last: {self.last_error}"

    def accept_command(self, data: Sequence[float], now: float, answers: int | None = None) -> str:
        """Take a command received at wall time ``now`` (s). Returns ACCEPTED, BAD (reason in
        ``last_error``) or, in lockstep, STALE when ``answers`` (the stamp of the state the command
        answers, if the sender says) is not the current state's."""
        arr = self._checked(data)
        if isinstance(arr, tuple):
            self.bad_commands += 1
            self._error = arr
            return BAD
        if answers is not None and self.config.mode == "lockstep" and answers != self.stamp_ns:
            self.stale_commands += 1
            return STALE
        self._command[:] = arr
        self._has_command = True
        self._command_time = now
        self._command_sim_time = self.clock_offset + self.env.data.time
        return ACCEPTED

    def accept_torque(self, tau: np.ndarray, now: float) -> str:
        """``accept_command`` for a composed controller's torque (a float array handed over by a
        direct call, not a message): the same checks in one compiled pass."""
        if tau.shape != (self.env.nu,) or not copy_if_finite(tau, self._command):
            return self.accept_command(tau, now)  # counted, with its reason
        self._has_command = True
        self._command_time = now
        self._command_sim_time = self.clock_offset + self.env.data.time
        return ACCEPTED

    @property
    def has_command(self) -> bool:
        """A valid command is waiting (lockstep) or held (realtime)."""
        return self._has_command

    def _apply(self, tau: np.ndarray, added: np.ndarray | None) -> None:
        """One step with ``tau``, of which ``added`` (None: nothing) is the driver's own gravity."""
        self.env.step(tau)  # clamps to the actuator limits; raises (no step) if not finite
        self._applied(added)

    def _applied(self, added: np.ndarray | None) -> None:
        self.torque[:] = self.env.last_torque
        if added is None:
            self.effort[:] = self.torque
        else:
            np.subtract(self.torque, added, out=self.effort)
        self.steps += 1

    def step_with(self, tau: np.ndarray) -> bool:
        """Lockstep with a composed controller: one physics step with ``tau`` (Nm, handed over by a
        direct call instead of a message), the command path without the copies. False, counted as a
        bad command and no step, when it is not ``nu`` finite values."""
        env = self.env
        if tau.shape != (env.nu,):
            ok, self._error = False, ("size", tau.size)
        elif self.config.driver_gravity_compensation:
            added = self.gravity()
            ok = env.step_if_finite(tau + added)  # the gravity of a broken state is not finite
        else:
            added = None
            ok = env.step_if_finite(tau)
        if not ok:
            self.bad_commands += 1
            if tau.shape == (env.nu,):
                self._error = ("finite", np.array(tau, dtype=np.float64))
            return False
        self._applied(added)
        self._has_command = False
        return True

    def _apply_command(self) -> None:
        """One step with the held command (plus the driver's gravity with driver_gravity_compensation)."""
        if self.config.driver_gravity_compensation:
            added = self.gravity()
            self._apply(self._command + added, added)
        else:
            self._apply(self._command.copy(), None)

    # ------------------------------------------------------------------ stepping
    def step_commanded(self) -> bool:
        """Lockstep: one physics step with the waiting command, which is used up. False if none waits."""
        if not self._has_command:
            return False
        self._apply_command()
        self._has_command = False
        return True

    def step_realtime(self, now: float) -> bool:
        """Realtime: one physics step with the last command, or the safe hold if it is older than
        ``command_timeout`` (or there never was one). Returns True while in the safe hold."""
        stale = not self._has_command or now - self._command_time > self.config.command_timeout
        if stale and not self.in_hold and self._has_command:
            self.command_timeouts += 1
            # in sim time: a process stalled by the machine stalls the physics too, so this is what the
            # arm saw, whatever the wall clock did
            self.hold_delay = self.sim_time - self._command_sim_time
        if stale:
            self.hold_steps += 1
            g = self.gravity()  # in the hold; with driver_gravity_compensation not the command's part
            self._apply(self.hold_torque(g), g if self.config.driver_gravity_compensation else None)
        else:
            self._hold_anchor = None  # the next hold anchors where it begins
            self._apply_command()
        self.in_hold = stale
        return stale

    # ------------------------------------------------------------------ episodes
    def reset(self, seed: int | None = None, q: np.ndarray | None = None) -> Observation:
        """Reset the world (``InsertionEnv.reset``); the clock continues; the held command is dropped.

        Raises ``ValueError`` for a rejected start configuration and leaves the world as it was.
        """
        env = self.env
        backup = mujoco.MjData(env.model)
        mujoco.mj_copyData(backup, env.model, env.data)
        last_torque = env.last_torque.copy()
        elapsed = env.time
        try:
            obs = env.reset(seed=seed, q=q)
        except (ValueError, RuntimeError):
            mujoco.mj_copyData(env.data, env.model, backup)
            env.last_torque[:] = last_torque
            mujoco.mj_forward(env.model, env.data)
            raise
        self.clock_offset += elapsed + self.dt  # strictly later than any stamp already published
        self._has_command = False
        self._hold_anchor = None  # a new world: a hold anchors at the reset state
        self.torque[:] = 0.0
        self.effort[:] = 0.0
        self.in_hold = True
        return obs
