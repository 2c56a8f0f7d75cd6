"""In-process rollouts: the deterministic controller every simulated millisecond, noise per decision.

Each episode runs ``decisions_per_episode`` RL decisions of ``steps_per_decision`` 1 ms physics
steps. At the start of decision k the policy noise eps_k ~ N(0, sigma^2) is drawn once and held
for the whole period, while the deterministic part u_mean(x, xdot) (the flow controller, or the
MLP) is re-evaluated every millisecond by the fast evaluator. For PPO the
action of decision k is a_k = u_mean(x_k, xdot_k) + eps_k at the decision's state; everything
else that happens within the period is part of the environment.

Arm tasks: ``FlowController`` maps the force to joint torques (Jacobian transpose, gravity
compensation, orientation impedance, limits). Block task (no arm): the force is applied to the
block directly, plus the simulator's bias force (gravity compensation).

Reward of decision k (``nf_core.reward``), from the state at the end of the period::

    r = -w |d|^2 - v ln((|d|^2 + a) / a) - c_v |xdot|^2 - c_u |a_k|^2,   d = x - x_goal

with every term reported separately (``reward_terms``); their sum is the reward.

The noise, the per-decision record, the reward and the log-densities come from the controller's
episode core (``nf_core.episode.EpisodeRun``), the same object the controller runs over
ROS; this module steps the simulated world and closes each decision with the simulator's state.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController, state_problem
from nf_controller_node.torque_law import TorqueLawConfig, excess_norm
from nf_core.episode import EpisodeRun, EpisodeSpec
from nf_core.friction import FrictionRanges
from nf_core.panda_spec import DQ_PLAUSIBLE_MAX, Q_PLAUSIBLE_MAX, Q_PLAUSIBLE_MIN
from nf_core.reward import RewardWeights
from nf_core.task_spec import held_part_inertia
from sim_bridge_node.env import InsertionEnv

from .config import TrainConfig

BLOCK_AXES = np.array([0, 2])  # the block moves in the world x-z plane


@dataclass
class EpisodeRecord:
    """One episode, one row per decision (arrays) plus per-episode summaries."""

    t: np.ndarray  # (K,) time of the decision in the episode, s
    x: np.ndarray  # (K, d) position the controller saw at the decision, m (controller frame)
    xdot: np.ndarray  # (K, d) velocity, m/s
    u_mean: np.ndarray  # (K, d) deterministic force at the decision, N
    action: np.ndarray  # (K, d) u_mean + held noise, N
    log_prob: np.ndarray  # (K,) log-density of the action under the behaviour policy
    reward: np.ndarray  # (K,)
    terms: dict[str, np.ndarray]  # REWARD_TERMS -> (K,), summing to reward
    depth: np.ndarray  # (K,) insertion depth at the end of the period, m
    success: np.ndarray  # (K,) bool, success at the end of the period
    start_seed: int | None
    final_distance: float  # |x - x_goal| at the end of the episode, m (true TCP)
    torque_norm: float  # mean over milliseconds of |tau - g(q)| (Nm; block: |force beyond gravity|, N)
    faults: int = 0  # controller faults (safe hold) during the episode
    info: dict = field(default_factory=dict)

    @property
    def episode_return(self) -> float:
        """Undiscounted sum of rewards."""
        return float(np.sum(self.reward))

    @property
    def final_success(self) -> bool:
        """Success at the end of the episode."""
        return bool(self.success[-1])


def friction_info(ranges: FrictionRanges, seed: int | None, n_joints: int) -> dict[str, list[float]]:
    """The joint friction of the episode with reset seed ``seed`` (``RolloutRunner.start_seed``'s value)
    as a record's ``info`` holds it (``friction_coulomb``, ``friction_viscous``: per joint): the draw
    ``InsertionEnv.reset(seed)`` applies, in process and in the sim node (the learner over ROS fills its
    records with it); {} when the ranges are off."""
    if not ranges.enabled:
        return {}
    coulomb, viscous = ranges.draw(seed, n_joints)
    return {"friction_coulomb": coulomb.tolist(), "friction_viscous": viscous.tolist()}


class RolloutRunner:
    """One simulated world plus (arm tasks) the Pinocchio model and ``FlowController``, reused per episode."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        self.task = cfg.task
        self.dim = cfg.dim
        self.weights = RewardWeights()
        self.env = InsertionEnv(cfg.task)
        self.friction = cfg.friction_ranges()
        self.env.set_friction_ranges(self.friction)  # each reset(seed) draws the episode's joint friction
        self.goal = self.env.goal_position
        self.arm: ArmModel | None = None
        self.controller: FlowController | None = None
        self._u = np.zeros(self.dim)  # the mean force of the state being answered
        self.on_step: Callable[[], None] | None = None  # called after every physics step (a video's frames)
        if cfg.task == "block":
            self.x_ref = self.goal[BLOCK_AXES].copy()
        else:
            # the controller's arm model carries the same part (mass, TCP) as the simulated hand
            self.arm = ArmModel(part=held_part_inertia(cfg.held_part))
            self.x_ref = self.goal.copy()
        if cfg.goal is not None:  # a goal measured on a real cell: the policy's x_ref and the reward's goal
            self.x_ref = np.asarray(cfg.goal, dtype=np.float64)

    def start_seed(self, seed: int | None) -> int | None:
        """The reset seed actually used (None for fixed starts)."""
        return None if self.cfg.start == "fixed" else seed

    def episode_spec(self, sigma: np.ndarray | None) -> EpisodeSpec:
        """The ``EpisodeSpec`` of one in-process episode: the config's length and decision period,
        noise std ``sigma`` (None: deterministic), the task's goal and reward weights."""
        cfg = self.cfg
        K, period = cfg.decisions_per_episode, cfg.decision_period
        return EpisodeSpec(episode_id=0, policy_version=0, duration=K * period, decision_period=period,
                           control_period=period / cfg.steps_per_decision,
                           sigma=sigma, noise_seed=0, x_goal=self.x_ref, weights=self.weights,
                           chunk_decisions=K)

    def run_episode(
        self,
        evaluator: object,
        sigma: np.ndarray | None,
        start_seed: int | None,
        noise_rng: np.random.Generator | None,
    ) -> EpisodeRecord:
        """Run one episode with the mean force of ``evaluator`` (``force(x, xdot, out)``) and noise
        of std ``sigma`` (shape (d,)) from ``noise_rng``; ``sigma`` None: deterministic controller.

        The episode itself (held noise, record, reward) is the controller's ``EpisodeRun``: this
        loop only steps the world and closes each decision with the simulator's state."""
        cfg = self.cfg
        K, P, d = cfg.decisions_per_episode, cfg.steps_per_decision, self.dim
        seed = self.start_seed(start_seed)
        self.env.reset(seed=seed)
        if sigma is not None:
            sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (d,)).copy()
            if noise_rng is None:
                raise ValueError("noise_rng is required when sigma is given")
        run = EpisodeRun(self.episode_spec(sigma), rng=noise_rng)
        period = self._arm_period if self.arm is not None else self._block_period
        if self.controller is None and self.arm is not None:
            # the law the policy carries to every controller (PolicyLaw), here as on the arm
            self.controller = FlowController(self.arm, evaluator, TorqueLawConfig().with_policy_law(cfg.policy_law()))
        if self.controller is not None:
            self.controller.set_evaluator(evaluator)
            self.controller.reset_rate_limit()
            self.controller.clear_fault()
        success = np.zeros(K, dtype=bool)
        faults = 0
        for k in range(K):
            faults += period(evaluator, run.noise(), P, run)[1]
            x, xdot = self.plant_state()
            run.close_period(x, xdot, self.env.insertion_depth)
            success[k] = self.env.success
        info = {}
        if self.env.episode_friction is not None:  # what this reset applied
            info = {"friction_coulomb": self.env.episode_friction[0].tolist(),
                    "friction_viscous": self.env.episode_friction[1].tolist()}
        return EpisodeRecord(
            t=run.decision_times(), x=run.x, xdot=run.xdot, u_mean=run.u_mean, action=run.action(),
            log_prob=run.log_prob(), reward=run.reward, terms=run.terms, depth=run.depth, success=success,
            start_seed=seed, final_distance=run.final_distance, torque_norm=run.mean_torque, faults=faults,
            info=info,
        )

    def plant_state(self) -> tuple[np.ndarray, np.ndarray]:
        """The simulator's position and velocity in the controller's frame (arm: the true TCP;
        block: its x-z plane), views of the simulator's state."""
        env = self.env
        if self.arm is None:
            return env.x[BLOCK_AXES], env.xdot[BLOCK_AXES]
        return env.x, env.xdot

    def _arm_period(self, ev: object, eps: np.ndarray, steps: int, run: EpisodeRun | None) -> tuple[float, int]:
        """``steps`` ms of the controller with held noise ``eps``, each state recorded in ``run``
        (if given); (sum of |tau - g| over the period, new faults)."""
        env, ctrl, arm, u = self.env, self.controller, self.arm, self._u
        total, fault = 0.0, 0
        for j in range(steps):
            had_fault = bool(ctrl.fault)
            q, dq = env.q, env.dq
            if not had_fault:  # the state check of the controller on the arm (ControlLoop): it holds there
                problem = state_problem(q, dq, Q_PLAUSIBLE_MIN, Q_PLAUSIBLE_MAX, DQ_PLAUSIBLE_MAX)
                if problem:
                    ctrl.fault = f"implausible joint state (code {problem}): the controller on the arm holds here"
            tau = ctrl.step(q, dq, eps)
            fault += int(bool(ctrl.fault) and not had_fault)
            torque = excess_norm(tau, arm.g)
            if run is not None:
                if j == 0:
                    ev.force(arm.x, ctrl.xdot, u)
                run.record(arm.x, ctrl.xdot, u, math.nan, torque)
            total += torque
            env.step(tau)
            if self.on_step is not None:
                self.on_step()
        return total, fault

    def _block_period(self, ev: object, eps: np.ndarray, steps: int, run: EpisodeRun | None) -> tuple[float, int]:
        """``steps`` ms of force control of the block (mean force + held noise + gravity
        compensation), each state recorded in ``run`` (if given); (sum of |force| beyond gravity, 0)."""
        env, u = self.env, self._u
        total = 0.0
        for _ in range(steps):
            x = env.x[BLOCK_AXES]
            xdot = env.xdot[BLOCK_AXES]
            ev.force(x, xdot, u)
            f = u + eps
            torque = math.sqrt(float(f @ f))
            if run is not None:
                run.record(x, xdot, u, math.nan, torque)
            total += torque
            env.step(f + env.bias_torques)
        return total, 0
