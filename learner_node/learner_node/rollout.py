"""In-process rollouts: the deterministic controller every simulated millisecond, noise per decision.

Each episode runs ``decisions_per_episode`` RL decisions of ``steps_per_decision`` 1 ms physics
steps. At the start of decision k the policy noise eps_k ~ N(0, sigma^2) is drawn once and held
for the whole period, while the deterministic part u_mean(x, xdot) (the flow controller, or the
MLP) is re-evaluated every millisecond by the fast evaluator (DESIGN section 4). For PPO the
action of decision k is a_k = u_mean(x_k, xdot_k) + eps_k at the decision's state; everything
else that happens within the period is part of the environment.

Arm tasks: ``FlowController`` maps the force to joint torques (Jacobian transpose, gravity
compensation, orientation impedance, limits). Block task (no arm): the force is applied to the
block directly, plus the simulator's bias force (gravity compensation).

Reward of decision k (DESIGN section 2), from the state at the end of the period::

    r = -w |d|^2 - v ln((|d|^2 + a) / a) - c_v |xdot|^2 - c_u |a_k|^2,   d = x - x_goal

with every term reported separately (``reward_terms``); their sum is the reward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from nf_controller_node import panda_spec
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_controller_node.reward import REWARD_TERMS, RewardWeights, gaussian_log_prob, reward_terms
from nf_controller_node.torque_law import excess_norm
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


class RolloutRunner:
    """One simulated world plus (arm tasks) the Pinocchio model and ``FlowController``, reused per episode."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.cfg = cfg
        self.task = cfg.task
        self.dim = cfg.dim
        self.weights = RewardWeights.from_config(cfg)
        plane = cfg.block_plane if cfg.task == "block" else "vertical"
        self.env = InsertionEnv(cfg.task, plane=plane)
        self.goal = self.env.goal_position
        self.arm: ArmModel | None = None
        self.controller: FlowController | None = None
        if cfg.task == "block":
            self.x_ref = self.goal[BLOCK_AXES].copy()
        else:
            # the controller's arm model carries the same part (mass, TCP) as the simulated hand
            self.arm = ArmModel(part=panda_spec.held_part_by_name("peg" if cfg.task == "peg" else "gear"))
            self.x_ref = self.goal.copy()

    def start_seed(self, seed: int | None) -> int | None:
        """The reset seed actually used (None for fixed starts)."""
        return None if self.cfg.start == "fixed" else seed

    def run_episode(
        self,
        evaluator: object,
        sigma: np.ndarray | None,
        start_seed: int | None,
        noise_rng: np.random.Generator | None,
    ) -> EpisodeRecord:
        """Run one episode with the mean force of ``evaluator`` (``force(x, xdot, out)``) and noise
        of std ``sigma`` (shape (d,)) from ``noise_rng``; ``sigma`` None: deterministic controller."""
        cfg = self.cfg
        K, P, d = cfg.decisions_per_episode, cfg.steps_per_decision, self.dim
        seed = self.start_seed(start_seed)
        self.env.reset(seed=seed)
        X, XD, U = np.zeros((K, d)), np.zeros((K, d)), np.zeros((K, d))
        E = np.zeros((K, d))
        Dist, Vel = np.zeros((K, d)), np.zeros((K, d))
        depth, success = np.zeros(K), np.zeros(K, dtype=bool)
        stochastic = sigma is not None
        if stochastic:
            sigma = np.broadcast_to(np.asarray(sigma, dtype=np.float64), (d,)).copy()
            if noise_rng is None:
                raise ValueError("noise_rng is required when sigma is given")
        run = self._arm_period if self.arm is not None else self._block_period
        if self.controller is None and self.arm is not None:
            self.controller = FlowController(self.arm, evaluator)
        if self.controller is not None:
            self.controller.set_evaluator(evaluator)
            self.controller.reset_rate_limit()
            self.controller.clear_fault()
        torque_sum, faults = 0.0, 0
        env = self.env
        for k in range(K):
            if stochastic:
                E[k] = sigma * noise_rng.standard_normal(d)
            tq, fault = run(evaluator, E[k], P, X[k], XD[k], U[k])
            torque_sum += tq
            faults += fault
            if self.arm is None:
                Dist[k] = env.x[BLOCK_AXES] - self.x_ref
                Vel[k] = env.xdot[BLOCK_AXES]
            else:
                Dist[k] = env.x - self.goal
                Vel[k] = env.xdot
            depth[k] = env.insertion_depth
            success[k] = env.success
        action = U + E
        terms = reward_terms(Dist, Vel, action, self.weights)
        reward = np.sum([terms[n] for n in REWARD_TERMS], axis=0)
        log_prob = gaussian_log_prob(E, sigma) if stochastic else np.zeros(K)
        return EpisodeRecord(
            t=np.arange(K) * cfg.decision_period, x=X, xdot=XD, u_mean=U, action=action, log_prob=log_prob,
            reward=reward, terms=terms, depth=depth, success=success, start_seed=seed,
            final_distance=float(np.linalg.norm(Dist[-1])), torque_norm=torque_sum / (K * P), faults=faults,
        )

    def _arm_period(self, ev: object, eps: np.ndarray, steps: int, x_out: np.ndarray, xdot_out: np.ndarray,
                    u_out: np.ndarray) -> tuple[float, int]:
        """``steps`` ms of the controller with held noise ``eps``; records the state at the first ms."""
        env, ctrl, arm = self.env, self.controller, self.arm
        total, fault = 0.0, 0
        for j in range(steps):
            had_fault = bool(ctrl.fault)
            tau = ctrl.step(env.q, env.dq, eps)
            fault += int(bool(ctrl.fault) and not had_fault)
            if j == 0:
                x_out[:] = arm.x
                xdot_out[:] = ctrl.xdot
                ev.force(arm.x, ctrl.xdot, u_out)
            total += excess_norm(tau, arm.g)
            env.step(tau)
        return total, fault

    def _block_period(self, ev: object, eps: np.ndarray, steps: int, x_out: np.ndarray, xdot_out: np.ndarray,
                      u_out: np.ndarray) -> tuple[float, int]:
        """``steps`` ms of force control of the block (mean force + held noise + gravity compensation)."""
        env = self.env
        u = np.empty(self.dim)
        total = 0.0
        for j in range(steps):
            x = env.x[BLOCK_AXES]
            xdot = env.xdot[BLOCK_AXES]
            ev.force(x, xdot, u)
            if j == 0:
                x_out[:] = x
                xdot_out[:] = xdot
                u_out[:] = u
            f = u + eps
            total += math.sqrt(float(f @ f))
            env.step(f + env.bias_torques)
        return total, 0
