"""The trainer's insertion task one RL decision at a time, for RL code of other projects (no ROS, no gymnasium).

``DecisionEnv`` drives the world and controller of the in-process rollouts (``RolloutRunner``):

- action: a task-space force (N, shape (dim,)) held for one decision period
  (``steps_per_decision`` physics steps of 1 ms) and applied every millisecond through the same path
  as the rollout's policy force: for the arm tasks ``FlowController`` (Jacobian transpose, gravity
  compensation, orientation impedance, joint damping, torque and rate limits, safe hold), for the
  block the force plus gravity compensation. The controller's own mean force is zero (``ZeroForce``),
  so the held action is the whole force, as the held noise is in the rollout;
- observation: what the MLP policy sees, ``[x - x_ref, xdot]`` (controller frame), at the start of
  the next decision;
- reward: the rollout's reward of the decision (``reward_terms`` of the state at the end of the
  period and the action), from the same episode core (``EpisodeRun``) as the rollout;
- episode: ``decisions_per_episode`` decisions (a time limit).

The held action is the mean force of a deterministic episode (``HeldForce``): the controller adds
it where the rollout adds its held noise, so ``RolloutRunner.run_episode(ZeroForce(dim), sigma,
start, rng)`` and this environment stepped
with that episode's actions from the same start produce the same states and rewards
(tests/test_gym_env.py). ``gym_env.InsertionGymEnv`` wraps it as a ``gymnasium.Env``.
"""

from __future__ import annotations

import math

import numpy as np

from nf_controller_node.controller import FlowController
from nf_core.episode import EpisodeRun

from ..config import TrainConfig
from ..rollout import BLOCK_AXES, RolloutRunner


class ZeroForce:
    """A mean-force evaluator that is zero everywhere (``FlowController``'s evaluator interface)."""

    def __init__(self, dim: int) -> None:
        self.dim = dim

    def force(self, x: np.ndarray, xdot: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """u = 0, written to ``out`` if given."""
        if out is None:
            return np.zeros(self.dim)
        out[:] = 0.0
        return out

    def potential(self, x: np.ndarray) -> float:
        """NaN: no potential."""
        return math.nan


class HeldForce(ZeroForce):
    """A mean-force evaluator that returns ``value`` everywhere (the action held for a decision)."""

    def __init__(self, dim: int) -> None:
        super().__init__(dim)
        self.value = np.zeros(dim)

    def force(self, x: np.ndarray, xdot: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """u = ``value``, written to ``out`` if given."""
        if out is None:
            return self.value.copy()
        out[:] = self.value
        return out


class DecisionEnv:
    """One simulated world of ``cfg``'s task, stepped one decision (held task-space force) at a time."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        self.runner = RolloutRunner(cfg)
        self.dim = cfg.dim
        self.horizon = cfg.decisions_per_episode
        self.held = HeldForce(self.dim)
        self.spec = self.runner.episode_spec(None)
        if self.runner.arm is not None:
            self.runner.controller = FlowController(self.runner.arm, self.held)
        self.run = EpisodeRun(self.spec)
        self.decision = 0  # decisions taken in the current episode

    def reset(self, start_seed: int | None) -> np.ndarray:
        """Start an episode as ``RolloutRunner.run_episode`` does with ``start_seed``; the first observation."""
        runner = self.runner
        runner.env.reset(seed=runner.start_seed(start_seed))
        if runner.controller is not None:
            runner.controller.reset_rate_limit()
            runner.controller.clear_fault()
        self.run = EpisodeRun(self.spec)
        self.decision = 0
        return self.observation()

    def observation(self) -> np.ndarray:
        """``[x - x_ref, xdot]`` of the current state, as the rollout records it at a decision (new array)."""
        runner, env = self.runner, self.runner.env
        if runner.arm is None:
            x, xdot = env.x[BLOCK_AXES], env.xdot[BLOCK_AXES]
        else:
            runner.arm.update(env.q, env.dq)  # what FlowController.step computes from the same joint state
            x, xdot = runner.arm.x, runner.arm.xdot
        return np.concatenate([x - runner.x_ref, xdot])

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, dict[str, float]]:
        """Hold ``action`` (N) for one decision period; (next observation, reward, episode over, info).

        ``info``: insertion ``depth`` (m) and ``success`` at the end of the period, the mean torque
        norm beyond gravity of the period (``torque_norm``) and new controller ``faults``.
        ``RuntimeError`` after the episode's last decision (call ``reset``).
        """
        runner, env, run, k = self.runner, self.runner.env, self.run, self.decision
        if k >= self.horizon:
            raise RuntimeError(f"the episode ended after {self.horizon} decisions: call reset() first")
        self.held.value[:] = np.asarray(action, dtype=np.float64).reshape(self.dim)
        period = runner._arm_period if runner.arm is not None else runner._block_period
        steps = self.cfg.steps_per_decision
        torque, faults = period(self.held, run.noise(), steps, run)
        x, xdot = runner.plant_state()
        run.close_period(x, xdot, env.insertion_depth)
        self.decision += 1
        info = {"depth": float(env.insertion_depth), "success": bool(env.success),
                "torque_norm": torque / steps, "faults": faults}
        return self.observation(), float(run.reward[k]), self.decision >= self.horizon, info
