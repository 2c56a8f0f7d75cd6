"""Training settings: one typed dataclass, loadable from a task's ROS 2 parameters YAML.

Precedence: the dataclass defaults (with per-task paper defaults for the fields left ``None``)
< the YAML file < command-line overrides. The YAML is the one file per task that every node
reads (``config/<task>.yaml``, ROS 2 ``ros__parameters`` format): settings shared by all nodes
sit under ``/**``, the learner's own under ``learner_node``. Keys under ``/**`` that are not
training settings belong to other nodes and are skipped; unknown keys under ``learner_node``
are errors (a typo must not pass silently).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from nf_core.flow_spec import ACTIVATIONS, FLOW_INITS
from nf_core.friction import FrictionRanges
from nf_core.reward import DEFAULT_WEIGHTS

TASKS = ("gear", "peg", "block", "gear_clamp")
POLICIES = ("nf", "mlp")
MLP_ACTIVATIONS = ("tanh", "gelu")
BASELINES = ("linear", "value")
ADV_NORMS = ("standardize", "center", "none")
STARTS = ("random", "fixed")
PLANES = ("vertical", "horizontal")
GAINS = ("fixed", "learned")
EXPLORATIONS = ("action", "params")
PARAM_FLOWS = ("all", "output", "subspace")
PARAM_STEPS = ("initial", "current")
PARAM_OPTIMIZERS = ("adam", "sgd")
PARAM_RATIOS = ("joint", "group")
PARAM_ADV_SCALES = ("batch", "running")
PARAM_SPREAD_SIGNALS = ("none", "pair_mean")
PHYSICS_DT = 0.001  # s, the simulator's (and controller's) step

# Paper settings per task (Khader et al., ICRA 2021); used for the fields left at None.
TASK_DEFAULTS: dict[str, dict[str, float | int]] = {
    "gear": {"episode_seconds": 5.0, "sigma_init": 5.0, "n_flow": 1, "n_hidden": 16, "stiffness": 4.0, "damping": 1.0},
    "peg": {"episode_seconds": 5.0, "sigma_init": 1.0, "n_flow": 2, "n_hidden": 16, "stiffness": 1.0, "damping": 1.0},
    # the gear task with a clamp across the approach (no paper values: the gear's)
    "gear_clamp": {"episode_seconds": 5.0, "sigma_init": 5.0, "n_flow": 1, "n_hidden": 16, "stiffness": 4.0,
                   "damping": 1.0},
    "block": {"episode_seconds": 4.0, "sigma_init": 2.0, "n_flow": 2, "n_hidden": 8, "stiffness": 1.0, "damping": 1.0},
}

YAML_SHARED = "/**"
YAML_NODE = "learner_node"


@dataclass
class TrainConfig:
    """All settings of one training run (NF-PPO or MLP-PPO on one task)."""

    task: str = "gear"
    """Task: gear (main), peg (peg-in-hole), block (2-D block insertion, no arm) or gear_clamp (the gear
    started behind a clamp it must be lifted over)."""
    policy: str = "nf"
    """Policy parameterisation: nf (stable normalizing-flow controller) or mlp (plain Gaussian MLP)."""
    sigma_init: float | None = None
    """Initial std of the Gaussian action noise, N (None: paper value, gear 5, peg 1, block 2)."""
    seed: int = 0
    """Seed of the policy initialisation and of every random draw of the run."""
    iterations: int = 100
    """PPO iterations (each: rollouts_per_iter episodes, then one update)."""
    rollouts_per_iter: int = 15
    """Episodes collected per iteration."""
    episode_seconds: float | None = None
    """Episode length, s of simulated time (None: gear 5, peg 5, block 4)."""
    decision_period: float = 0.01
    """RL decision period, s: the policy noise is drawn once per period and held (multiple of 1 ms)."""
    start: str = "random"
    """Start states: random (joints ~ N(q_mean, 0.2 rad); block ~ N(mean, diag 50 mm, 100 mm)) or fixed."""
    block_plane: str = "vertical"
    """Block task only: vertical (gravity along the insertion, compensated) or horizontal."""
    n_flow: int | None = None
    """Flow elements (2 coupling layers each) (None: gear 1, peg 2, block 2)."""
    n_hidden: int | None = None
    """Hidden units of the flow's s/t networks (None: gear 16, peg 16, block 8)."""
    activation: str = "gelu"
    """Activation of the flow's s/t networks (gelu, tanh, softplus)."""
    flow_init: str = "random"
    """Flow initialisation: random (torch's default for every layer) or identity (output layers of
    the s/t networks zero, so the untrained controller is the impedance law with S and D)."""
    stiffness: float | None = None
    """S = stiffness * I in the flow's latent space (None: gear 4, peg 1, block 1)."""
    damping: float | None = None
    """D = damping * I in the flow's latent space (None: 1 for all tasks)."""
    stiffness_axial: float | None = None
    """S entry of the last (insertion, z) axis, replacing ``stiffness`` there (None: isotropic S)."""
    damping_axial: float | None = None
    """D entry of the last (insertion, z) axis, replacing ``damping`` there (None: isotropic D)."""
    potential_force_bound: float = 0.0
    """Bound on the flow potential's pull, N in the latent space (``TorqueLawConfig.potential_force_bound``):
    beyond it the potential grows linearly, so a stiff policy started far from x_ref does not drive the
    joints into their torque limits, where the stability proof does not reach. 0: off. A shared (``/**``)
    setting: the controller node reads the same key. Parameter exploration only."""
    stiffness_floor: float = 0.0
    """Learned gains: no diagonal entry of S (N/m, latent) below it, in every draw, the mean and a loaded
    policy (lifted onto it). An arm's joint friction stalls a soft spring that a frictionless simulation
    inserts with (docs/hardware.md); run_robot sets 250 for a policy from a checkpoint. 0: off."""
    gains: str = "fixed"
    """NF policy: fixed (S, D as set above) or learned (their diagonals, through exp, start at the values
    above: every value stays symmetric positive definite, so the stability proof holds throughout)."""
    exploration: str = "action"
    """NF policy: action (Gaussian force noise held per decision; PPO per decision) or params (every rollout
    runs the deterministic controller with parameters drawn around the policy's; PPO per rollout)."""
    param_sigma_gains: float = 0.3
    """exploration=params: initial std of the perturbation of ln S and ln D (per diagonal entry)."""
    param_sigma_flow: float = 0.0
    """exploration=params: initial std of the perturbation of every flow weight (0: the flow is not explored
    and stays as initialised)."""
    param_flow: str = "all"
    """exploration=params, param_sigma_flow > 0: which flow weights are explored: all, or output (the output
    layers of the s/t networks; the hidden layers stay as initialised, random features of the input), or
    subspace (param_flow_dim fixed random directions in those output layers' weights)."""
    param_flow_dim: int = 8
    """exploration=params, param_flow=subspace: number of explored directions in the flow's weights."""
    flow_input_scale: float = 0.0
    """NF policy: m; > 0: the flow's coupling nets see (x - x_ref) / flow_input_scale and translate in
    units of it (the weights are initialised, and explored, in those units; the controller receives the
    equivalent physical weights). 0: the nets see x in metres."""
    param_lr: float = 0.05
    """exploration=params: Adam step size of the parameter-space mean, in units of its exploration std."""
    param_lr_flow: float = 0.0
    """exploration=params: the flow mean's Adam step in units of its std (0: param_lr)."""
    param_optimizer: str = "adam"
    """exploration=params: the mean's optimiser. adam: every coordinate moves about param_lr stds per step
    whatever its gradient's size; sgd: the search-gradient step of evolution strategies, param_lr stds per
    step times the correlation of the advantages with that coordinate's draws, so coordinates the returns
    do not follow stay put (``param_explore.make_param_optimizer``)."""
    param_ratio: str = "joint"
    """exploration=params: one PPO ratio over all explored parameters (joint) or one per group (group:
    gains and flow; the distribution factorises, so each is that group's own likelihood ratio)."""
    param_adv_scale: str = "batch"
    """exploration=params: the pairs' advantages are divided by this iteration's RMS (batch) or by the mean
    RMS of all iterations so far (running: iterations whose rollouts differ little step little)."""
    param_spread_signal: str = "none"
    """exploration=params: what the PPO update gives the exploration stds. none: the pairs' advantages
    only; they are antisymmetric in the mirrored draws, so the stds' gradient is zero at the start of
    each update and ``param_sigma_lr`` moves them by noise. pair_mean: both members of a pair also get
    the pair's mean return less the batch's (as PGPE's std update, Sehnke et al. 2010): the spread
    narrows when the wider draws do worse and widens when they do better; the mean's gradient is
    unchanged (a symmetric advantage cancels in it)."""
    param_step: str = "initial"
    """exploration=params: the mean's Adam step is param_lr times the group's initial std (initial), or its
    std at each update (current: the step shrinks with the exploration, so one update moves the mean by
    the same number of stds, and the same KL, late as early)."""
    param_sigma_lr: float = 0.05
    """exploration=params: Adam step size of the exploration log-stds (0: the stds stay fixed)."""
    param_sigma_decay: float = 1.0
    """exploration=params: factor on the exploration stds after every update (1: none), so the rollouts
    come closer to the learned controller as training goes on."""
    param_sigma_settle: float = 1.0
    """exploration=params: an extra factor on the exploration stds after an update whose rollout of the mean
    itself (the odd last rollout) succeeded while fewer than ``param_settle_success`` of the draws did
    (1: off). Once the mean inserts, the draws that fail are only spread: they narrow at this rate then,
    and not before (a faster plain decay narrows them before the mean has arrived)."""
    param_settle_success: float = 0.9
    """exploration=params: the draws' success rate below which ``param_sigma_settle`` applies."""
    param_settle_rule: str = "mean"
    """exploration=params: when ``param_sigma_settle`` applies. mean: the mean's own rollout succeeded (a fixed
    start: that rollout says the mean has arrived) | batch: the whole batch's success rate is at least
    ``param_settle_from`` (random starts: one rollout of the mean from its own start says little)."""
    param_settle_from: float = 0.6
    """exploration=params, ``param_settle_rule`` batch: the batch success rate from which the spread settles."""
    param_elite: str = "none"
    """exploration=params: none (PPO's update only) | succeeded: after an update whose rollout of the mean
    (the odd last one) failed while some draws succeeded, the mean moves to the average of the succeeded
    draws (a cross-entropy step: one update goes where PPO's clipped trust region needs several) | returns: as
    succeeded, and while no draw succeeds, to the best quarter of the draws by return if each beat the mean's
    own rollout | minority: after any update in which some rollouts succeeded but fewer than half, the mean's
    own included, the mean moves to the average of the rollouts that succeeded (so a mean that inserts at the
    edge of the gains that do is not moved off them by PPO's step, and moves inwards when draws beyond it
    insert too) | minority_returns: as minority, and while no rollout succeeds, as returns. Any draw is a
    stable controller, so the jump keeps every rollout stable."""
    param_sigma_jump: float = 1.0
    """exploration=params: a factor on the exploration stds when ``param_elite`` moves the mean onto rollouts
    that succeeded (not by return; 1: off). Fewer than half of the draws inserting says the gains that insert
    are a narrow set next to the spread: the next draws are narrowed at once, not an update later."""
    mlp_hidden: int = 64
    """MLP policy: units per hidden layer (two hidden layers)."""
    mlp_activation: str = "tanh"
    """MLP policy: hidden activation (tanh or gelu)."""
    learning_rate: float = 2.5e-4
    """Adam step size."""
    update_epochs: int = 10
    """Passes over the batch per PPO update."""
    minibatch_size: int = 64
    """Decisions per gradient step."""
    clip_coef: float = 0.2
    """PPO ratio clip epsilon."""
    gamma: float = 0.99
    """Discount per decision."""
    gae_lambda: float = 0.97
    """GAE lambda."""
    adv_norm: str = "standardize"
    """Advantage normalisation over the whole batch: standardize (centre, divide by std), center, none."""
    baseline: str = "linear"
    """Baseline: linear (least-squares features of observation and time, as the authors) or value (MLP)."""
    vf_coef: float = 0.5
    """Weight of the value loss (baseline=value only)."""
    value_hidden: int = 64
    """Units per hidden layer of the value network (baseline=value only)."""
    max_grad_norm: float = 0.0
    """Clip the gradient norm to this value (0: no clipping)."""
    target_kl: float = 0.0
    """Stop an update once a minibatch shows approx_kl > 1.5 x this before its step, as
    stable-baselines3 does (0: never)."""
    reward_w: float = DEFAULT_WEIGHTS.w
    """Reward weight w of the squared distance |d|^2 (defaults and meanings: ``nf_core.reward``)."""
    reward_v: float = DEFAULT_WEIGHTS.v
    """Reward weight v of the log-distance term v ln((|d|^2 + a) / a)."""
    reward_a: float = DEFAULT_WEIGHTS.a
    """Offset a of the log-distance term, m^2."""
    reward_velocity: float = DEFAULT_WEIGHTS.velocity
    """Reward weight of the squared TCP speed |xdot|^2 (m/s)."""
    reward_action: float = DEFAULT_WEIGHTS.action
    """Reward weight of the squared action force |u|^2 (N)."""
    friction_coulomb: list[float] = field(default_factory=lambda: [0.0, 0.0])
    """Simulation: Coulomb joint friction (MuJoCo frictionloss) [lo, hi], Nm (block: N), drawn per joint
    uniformly for every episode from its start seed (``nf_core.friction``), held-out evaluation starts
    included; shared (``/**``): the sim node applies the same draw over ROS. [0, 0]: none (the default)."""
    friction_viscous: list[float] = field(default_factory=lambda: [0.0, 0.0])
    """Simulation: viscous joint friction [lo, hi], Nm s/rad, added to the arm's own damping, drawn like
    ``friction_coulomb`` (same stream, after it). [0, 0]: none (the default)."""
    eval_episodes: int = 10
    """Final evaluation: episodes of the deterministic controller from held-out starts (1 if start=fixed)."""
    eval_every: int = 0
    """Also evaluate the deterministic controller on the same held-out starts after every ``eval_every``-th
    iteration (0: only before and after training): the metrics' ``eval_success``, ``eval_return`` and
    ``eval_final_distance`` (NaN in the other rows), ``evaluations/iteration_NNNN.json`` and the
    curves' markers. It draws nothing from the training's random streams; over ROS it costs
    ``eval_episodes`` episodes of the arm each time."""
    goal: list[float] | None = None
    """The controller's x_ref and the reward's goal, m in the robot's base frame (3 values; block: x, z).
    None: the simulated task's goal (gear and peg [0.5, 0, 0.07]). On a real cell, the goal measured
    there (the Franka driver's ``goal``): the simulated one would aim at wherever the simulated
    fixture happens to be."""
    init_checkpoint: str = ""
    """A new run that starts from another run's policy: that run's ``checkpoint.pt`` ('': the policy as
    the settings above initialise it). Loaded as learned: the flow weights, S and D, and the exploration
    spread as the checkpoint left it (the action noise's log-std; with exploration=params the parameter
    stds, decayed and learned, not ``param_sigma_*``: fine-tuning explores near the policy). Fresh: the
    iteration counter, optimiser, baseline, random streams, metrics and run folder. x_ref is this run's
    goal (``goal``, else the task's), never the checkpoint's. Its architecture (policy; n_flow, n_hidden,
    activation or mlp_hidden, mlp_activation; the task's dimension) must be this config's. Read only if
    the run folder has no checkpoint of its own (that one is resumed)."""
    init_sigma_scale: float = 1.0
    """With ``init_checkpoint``: factor on the loaded exploration stds (parameter stds, or the action
    noise), in (0, 1]. Below 1 the rollouts on the new system stay closer to the loaded controller and,
    the mean's step being measured in stds (``param_step``), each update moves it less."""
    init_target_kl: float = 0.02
    """With ``init_checkpoint``: ``target_kl`` of the fine-tuning run, in place of ``target_kl`` (0: that
    one). A loaded policy that already inserts is kept near: without it one update moved a zero-shot
    10/10 policy to 4/10 on franky-sim (approx_kl 0.5-1.6 per update; docs/measurements.md)."""

    @property
    def eval_starts(self) -> int:
        """Episodes of a held-out evaluation: ``eval_episodes``, at most 1 with fixed starts (all alike)."""
        return min(self.eval_episodes, 1) if self.start == "fixed" else self.eval_episodes

    @property
    def update_target_kl(self) -> float:
        """The ``target_kl`` the updates use: ``init_target_kl`` when fine-tuning, else ``target_kl``."""
        return self.init_target_kl if self.init_checkpoint and self.init_target_kl > 0.0 else self.target_kl

    def __post_init__(self) -> None:
        self._coerce_types()
        if self.task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {self.task!r}")
        for name, value in TASK_DEFAULTS[self.task].items():
            if getattr(self, name) is None:
                setattr(self, name, value)
        self.validate()

    # ------------------------------------------------------------------ validation
    def _coerce_types(self) -> None:
        """Check each value against its annotation; ints are accepted for float fields."""
        hints = typing.get_type_hints(TrainConfig)
        for f in fields(self):
            setattr(self, f.name, _coerce(f.name, getattr(self, f.name), hints[f.name]))

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first bad setting and why."""
        _choice("policy", self.policy, POLICIES)
        _choice("start", self.start, STARTS)
        _choice("block_plane", self.block_plane, PLANES)
        _choice("activation", self.activation, ACTIVATIONS)
        _choice("flow_init", self.flow_init, FLOW_INITS)
        _choice("mlp_activation", self.mlp_activation, MLP_ACTIVATIONS)
        _choice("baseline", self.baseline, BASELINES)
        _choice("adv_norm", self.adv_norm, ADV_NORMS)
        _choice("gains", self.gains, GAINS)
        _choice("exploration", self.exploration, EXPLORATIONS)
        _positive("param_sigma_gains", self.param_sigma_gains)
        _non_negative("param_sigma_flow", self.param_sigma_flow)
        _choice("param_flow", self.param_flow, PARAM_FLOWS)
        _choice("param_step", self.param_step, PARAM_STEPS)
        _choice("param_optimizer", self.param_optimizer, PARAM_OPTIMIZERS)
        _int_range("param_flow_dim", self.param_flow_dim, 1, 100_000)
        _choice("param_ratio", self.param_ratio, PARAM_RATIOS)
        _choice("param_adv_scale", self.param_adv_scale, PARAM_ADV_SCALES)
        _choice("param_spread_signal", self.param_spread_signal, PARAM_SPREAD_SIGNALS)
        _non_negative("param_lr_flow", self.param_lr_flow)
        _non_negative("potential_force_bound", self.potential_force_bound)
        _non_negative("stiffness_floor", self.stiffness_floor)
        if self.stiffness_floor > 0.0 and (self.gains != "learned" or self.policy != "nf"):
            raise ValueError("stiffness_floor needs the nf policy with gains: learned (it bounds the learned S)")
        if self.potential_force_bound > 0.0 and self.exploration == "action":
            raise ValueError("potential_force_bound needs exploration=params: the learner's differentiable force "
                             "(action noise's likelihood) has no bound")
        _non_negative("flow_input_scale", self.flow_input_scale)
        _positive("param_lr", self.param_lr)
        _non_negative("param_sigma_lr", self.param_sigma_lr)
        if not 0.0 < self.param_sigma_decay <= 1.0:
            raise ValueError(f"param_sigma_decay must be in (0, 1], got {self.param_sigma_decay}")
        if not 0.0 < self.param_sigma_settle <= 1.0:
            raise ValueError(f"param_sigma_settle must be in (0, 1], got {self.param_sigma_settle}")
        if not 0.0 <= self.param_settle_success <= 1.0:
            raise ValueError(f"param_settle_success must be in [0, 1], got {self.param_settle_success}")
        if self.param_settle_rule not in ("mean", "batch"):
            raise ValueError(f"param_settle_rule must be mean or batch, got {self.param_settle_rule!r}")
        if not 0.0 <= self.param_settle_from <= 1.0:
            raise ValueError(f"param_settle_from must be in [0, 1], got {self.param_settle_from}")
        if self.param_sigma_settle < 1.0 and self.param_settle_rule == "mean" and self.rollouts_per_iter % 2 == 0:
            raise ValueError("param_sigma_settle with param_settle_rule mean needs an odd rollouts_per_iter: the "
                             "last rollout runs the mean")
        if self.param_elite not in ("none", "succeeded", "returns", "minority", "minority_returns"):
            raise ValueError("param_elite must be none, succeeded, returns, minority or minority_returns, "
                             f"got {self.param_elite!r}")
        if not 0.0 < self.param_sigma_jump <= 1.0:
            raise ValueError(f"param_sigma_jump must be in (0, 1], got {self.param_sigma_jump}")
        if self.param_elite != "none" and self.rollouts_per_iter % 2 == 0:
            raise ValueError("param_elite needs an odd rollouts_per_iter: the last rollout runs the mean")
        if self.exploration == "params" and self.gains == "fixed" and self.param_sigma_flow == 0.0:
            raise ValueError("exploration=params needs something to explore: gains=learned or param_sigma_flow > 0")
        _positive("sigma_init", self.sigma_init)
        _positive("episode_seconds", self.episode_seconds)
        _positive("decision_period", self.decision_period)
        _positive("stiffness", self.stiffness)
        _positive("damping", self.damping)
        for name in ("stiffness_axial", "damping_axial"):
            if getattr(self, name) is not None:
                _positive(name, getattr(self, name))
        _positive("learning_rate", self.learning_rate)
        _positive("reward_a", self.reward_a)
        for name in ("reward_w", "reward_v", "reward_velocity", "reward_action", "vf_coef", "max_grad_norm",
                     "target_kl", "init_target_kl"):
            _non_negative(name, getattr(self, name))
        _int_range("seed", self.seed, 0, 2**32 - 1)
        _int_range("iterations", self.iterations, 1, 1_000_000)
        _int_range("rollouts_per_iter", self.rollouts_per_iter, 1, 100_000)
        _int_range("n_flow", self.n_flow, 1, 64)
        _int_range("n_hidden", self.n_hidden, 1, 1024)
        _int_range("mlp_hidden", self.mlp_hidden, 1, 4096)
        _int_range("value_hidden", self.value_hidden, 1, 4096)
        _int_range("update_epochs", self.update_epochs, 1, 10_000)
        _int_range("minibatch_size", self.minibatch_size, 1, 10_000_000)
        _int_range("eval_episodes", self.eval_episodes, 0, 100_000)
        _int_range("eval_every", self.eval_every, 0, 100_000)
        friction = self.friction_ranges()  # ValueError naming the range
        if friction.randomized and self.start == "fixed":
            raise ValueError("friction_coulomb / friction_viscous are drawn from each episode's start seed; with "
                             "start: fixed there is none (every episode would get the ranges' middles): use "
                             "start: random, or give each range one value ([x, x])")
        if not (0.0 < self.init_sigma_scale <= 1.0):
            raise ValueError(f"init_sigma_scale must be in (0, 1], got {self.init_sigma_scale}")
        if self.init_checkpoint != self.init_checkpoint.strip():
            raise ValueError(f"init_checkpoint must be a path without leading or trailing spaces, "
                             f"got {self.init_checkpoint!r}")
        if self.goal is not None and len(self.goal) != self.dim:
            raise ValueError(f"goal must have {self.dim} values (m) for the {self.task} task, got {self.goal}")
        if not 0.0 < self.clip_coef < 1.0:
            raise ValueError(f"clip_coef must be in (0, 1), got {self.clip_coef}")
        for name in ("gamma", "gae_lambda"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {value}")
        steps = self.decision_period / PHYSICS_DT
        if abs(steps - round(steps)) > 1e-9 * max(1.0, steps):
            raise ValueError(
                f"decision_period must be a whole multiple of the {PHYSICS_DT * 1e3:g} ms physics step, "
                f"got {self.decision_period} s"
            )
        decisions = self.episode_seconds / self.decision_period
        if self.episode_seconds < self.decision_period or abs(decisions - round(decisions)) > 1e-9 * decisions:
            raise ValueError(
                f"episode_seconds ({self.episode_seconds} s) must be a whole multiple of decision_period "
                f"({self.decision_period} s)"
            )

    # ------------------------------------------------------------------ derived values
    @property
    def dim(self) -> int:
        """Task-space dimension: 2 for the block (x, z), 3 for the arm tasks."""
        return 2 if self.task == "block" else 3

    def friction_ranges(self) -> FrictionRanges:
        """The per-episode joint friction ranges (``nf_core.friction``; off when both are [0, 0])."""
        return FrictionRanges(tuple(self.friction_coulomb), tuple(self.friction_viscous))

    def stiffness_matrix(self) -> np.ndarray:
        """S: ``stiffness`` on every axis, ``stiffness_axial`` (if set) on the last (insertion) axis."""
        return _diagonal(self.dim, self.stiffness, self.stiffness_axial)

    def damping_matrix(self) -> np.ndarray:
        """D: ``damping`` on every axis, ``damping_axial`` (if set) on the last (insertion) axis."""
        return _diagonal(self.dim, self.damping, self.damping_axial)

    @property
    def steps_per_decision(self) -> int:
        """Physics (1 ms) steps per decision period."""
        return round(self.decision_period / PHYSICS_DT)

    @property
    def decisions_per_episode(self) -> int:
        """Decisions per episode."""
        return round(self.episode_seconds / self.decision_period)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of all fields (resolved values)."""
        return dataclasses.asdict(self)

    @staticmethod
    def with_defaults(stored: dict[str, Any]) -> dict[str, Any]:
        """A stored config (checkpoint, config.json) with every setting added since it was written
        filled in by its task's default, which is what that run used."""
        return {**TrainConfig(task=stored["task"]).to_dict(), **stored}

    def table(self) -> str:
        """The settings as an aligned two-column text table, for the log at the start of a run."""
        rows = [(f.name, repr(getattr(self, f.name))) for f in fields(self)]
        width = max(len(n) for n, _ in rows)
        line = f"+-{'-' * width}-+-{'-' * max(len(v) for _, v in rows)}-+"
        vwidth = len(line) - width - 7
        out = [line, f"| {'setting':<{width}} | {'value':<{vwidth}} |", line]
        out += [f"| {n:<{width}} | {v:<{vwidth}} |" for n, v in rows]
        out.append(line)
        return "\n".join(out)

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_sources(
        cls, yaml_path: str | Path | None = None, overrides: dict[str, Any] | None = None
    ) -> TrainConfig:
        """Defaults < ``yaml_path`` (a task's parameters file) < ``overrides`` (values or strings)."""
        values: dict[str, Any] = {}
        if yaml_path is not None:
            for key, value in read_yaml_params(yaml_path).items():
                # YAML 1.1 reads 1e-5 (no dot) as a string: parse strings of numeric settings
                values[key] = parse_value(key, value) if isinstance(value, str) else value
        for key, value in (overrides or {}).items():
            if key not in _FIELD_NAMES:
                raise ValueError(f"unknown setting {key!r}; known settings: {', '.join(sorted(_FIELD_NAMES))}")
            values[key] = parse_value(key, value) if isinstance(value, str) else value
        return cls(**values)


def _diagonal(dim: int, value: float, axial: float | None) -> np.ndarray:
    diag = np.full(dim, float(value))
    if axial is not None:
        diag[-1] = axial
    return np.diag(diag)


_FIELD_NAMES = frozenset(f.name for f in fields(TrainConfig))


def read_yaml_params(path: str | Path) -> dict[str, Any]:
    """Training settings from a ROS 2 parameters YAML: ``/**`` (shared, other keys skipped) then
    ``learner_node`` (unknown keys are errors). Nested parameter groups are flattened with dots."""
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise ValueError(f"cannot read config {path}: {exc}") from None
    except yaml.YAMLError as exc:
        raise ValueError(f"config {path} is not valid YAML: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"config {path}: expected a mapping of node names to ros__parameters")
    out: dict[str, Any] = {}
    for section, strict in ((YAML_SHARED, False), (YAML_NODE, True)):
        if section not in doc:
            continue
        body = doc[section]
        if not isinstance(body, dict) or not isinstance(body.get("ros__parameters"), dict):
            raise ValueError(f"config {path}: section {section!r} needs a 'ros__parameters' mapping")
        for key, value in _flatten(body["ros__parameters"]).items():
            if key in _FIELD_NAMES:
                out[key] = value
            elif strict:
                raise ValueError(f"config {path}: unknown learner_node parameter {key!r}")
    return out


def _flatten(params: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def parse_value(name: str, text: str) -> Any:
    """Parse a command-line string for setting ``name`` according to its type."""
    hint = typing.get_type_hints(TrainConfig)[name]
    if _allows_none(hint) and text.strip().lower() in ("none", "null", "~", ""):
        return None
    base = _base_type(hint)
    if typing.get_origin(base) is list:  # "0.5,0,0.05" or "[0.5, 0, 0.05]"
        return [part.strip() for part in text.strip().strip("[]").split(",") if part.strip()]
    try:
        if base is int:
            return int(text)
        if base is float:
            return float(text)
    except ValueError:
        raise ValueError(f"{name}: expected {base.__name__}, got {text!r}") from None
    return text


def _allows_none(hint: Any) -> bool:
    return isinstance(hint, types.UnionType) and type(None) in typing.get_args(hint)


def _base_type(hint: Any) -> type:
    if isinstance(hint, types.UnionType):
        return next(a for a in typing.get_args(hint) if a is not type(None))
    return hint


def _coerce(name: str, value: Any, hint: Any) -> Any:
    if value is None and _allows_none(hint):
        return None
    base = _base_type(hint)
    if base is float and isinstance(value, int | float) and not isinstance(value, bool):
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value}")
        return value
    if base is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if base is str and isinstance(value, str):
        return value
    if typing.get_origin(base) is list and not isinstance(value, str | bytes | dict):
        try:
            items = [float(v) for v in value]
        except (TypeError, ValueError):
            raise ValueError(f"{name} must be a list of numbers, got {value!r}") from None
        if not all(math.isfinite(v) for v in items):
            raise ValueError(f"{name} must be finite, got {items}")
        return items
    raise ValueError(f"{name} must be {base.__name__}, got {value!r} ({type(value).__name__})")


def _choice(name: str, value: str, allowed: tuple[str, ...]) -> None:
    if value not in allowed:
        raise ValueError(f"{name} must be one of {allowed}, got {value!r}")


def _positive(name: str, value: float) -> None:
    if not value > 0.0:
        raise ValueError(f"{name} must be > 0, got {value}")


def _non_negative(name: str, value: float) -> None:
    if not value >= 0.0:
        raise ValueError(f"{name} must be >= 0, got {value}")


def _int_range(name: str, value: int, lo: int, hi: int) -> None:
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be in [{lo}, {hi}], got {value}")
