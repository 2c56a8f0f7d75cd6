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

from nf_core.flow_spec import FLOW_INITS
from nf_core.friction import FrictionRanges
from nf_core.policy_params import PolicyLaw
from nf_core.task_spec import TaskFileError, load_task, task_path

TASKS = ("gear", "peg", "block", "gear_clamp")  # built in; any task file (a path) is a task too
POLICIES = ("nf", "mlp")
STARTS = ("random", "fixed")
GAINS = ("fixed", "learned")
EXPLORATIONS = ("action", "params")
SETTLE_RULES = ("mean", "batch")
ELITES = ("none", "minority_returns")
PHYSICS_DT = 0.001  # s, the simulator's (and controller's) step
# Fixed parts of the method (not settings): the flow's s/t activation, the MLP policy's size, the
# advantage normalisation (standardised over the batch) and the baseline (a linear feature fit).
FLOW_ACTIVATION = "gelu"
MLP_HIDDEN = 64
MLP_ACTIVATION = "tanh"

# Paper settings per task (Khader et al., ICRA 2021); used for the fields left at None.
TASK_DEFAULTS: dict[str, dict[str, float | int]] = {
    "gear": {"episode_seconds": 5.0, "sigma_init": 5.0, "n_flow": 1, "n_hidden": 16, "stiffness": 4.0, "damping": 1.0},
    "peg": {"episode_seconds": 5.0, "sigma_init": 1.0, "n_flow": 2, "n_hidden": 16, "stiffness": 1.0, "damping": 1.0},
    "gear_clamp": {"episode_seconds": 5.0, "sigma_init": 5.0, "n_flow": 1, "n_hidden": 16, "stiffness": 4.0,
                   "damping": 1.0},
    "block": {"episode_seconds": 4.0, "sigma_init": 2.0, "n_flow": 2, "n_hidden": 8, "stiffness": 1.0, "damping": 1.0},
}

TASK_FILE_KEY = "task_file"  # a stored config's copy of its task file's text


def materialise_task(text: str) -> Path:
    """A stored task file's text as a file here (the user's cache, named by its hash): for a checkpoint
    whose task file is not on this machine."""
    import hashlib
    import os

    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "nf-control" / "tasks"
    path = cache / f"{hashlib.sha256(text.encode()).hexdigest()[:16]}.yaml"
    if not path.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return path


YAML_SHARED = "/**"
YAML_NODE = "learner_node"

# Settings that were removed, with what replaced them: a stored run (checkpoint, config.json) that has
# one is read if its value is what the code now always does, refused otherwise (docs/results/removed_settings.md).
REMOVED_SETTINGS: dict[str, object] = {
    "activation": FLOW_ACTIVATION, "mlp_hidden": MLP_HIDDEN, "mlp_activation": MLP_ACTIVATION,
    "baseline": "linear", "adv_norm": "standardize", "vf_coef": None, "value_hidden": None,
    "max_grad_norm": 0.0, "target_kl": 0.0, "block_plane": "vertical", "damping_axial": None,
    "reward_w": 1.0, "reward_v": 2.0, "reward_a": 1e-5, "reward_velocity": 0.1, "reward_action": 1e-3,
    "param_lr_flow": 0.0, "param_optimizer": "adam", "param_spread_signal": "none", "param_step": "current",
    "param_adv_scale": "running", "param_ratio": "group", "param_flow": "subspace", "param_settle_success": 0.9,
    "init_sigma_scale": 1.0,
}


@dataclass
class TrainConfig:
    """All settings of one training run (NF-PPO or MLP-PPO on one task); docs/learner.md."""

    # --- task --------------------------------------------------------------------------------------
    task: str = "gear"
    """gear | peg | block (2-D, no arm) | gear_clamp (the gear behind a clamp)."""
    episode_seconds: float | None = None
    """s of simulated time per episode (None: gear 5, peg 5, block 4)."""
    decision_period: float = 0.01
    """s; reward and log period, and the hold time of the action noise (a multiple of 1 ms)."""
    start: str = "random"
    """random (joints ~ N(q_mean, 0.2 rad); block ~ N(mean, diag 50 mm, 100 mm)) | fixed."""
    goal: list[float] | None = None
    """m, base frame: the controller's x_ref and the reward's goal (3 values; block: x, z). None: the task's."""
    friction_coulomb: list[float] = field(default_factory=lambda: [0.0, 0.0])
    """Nm (block: N), [lo, hi]: joint Coulomb friction drawn per joint and episode from its start seed."""
    friction_viscous: list[float] = field(default_factory=lambda: [0.0, 0.0])
    """Nm s/rad, [lo, hi]: viscous joint friction added to the arm's own, drawn like friction_coulomb."""

    # --- policy ------------------------------------------------------------------------------------
    policy: str = "nf"
    """nf (the stable normalizing-flow controller) | mlp (a plain Gaussian MLP, for comparison)."""
    n_flow: int | None = None
    """flow elements, 2 coupling layers each (None: gear 1, peg 2, block 2)."""
    n_hidden: int | None = None
    """hidden units of the coupling layers' s/t networks (None: gear 16, peg 16, block 8)."""
    flow_init: str = "random"
    """random (torch's default) | identity (phi(x) = x: the prior is the impedance law with S and D)."""
    flow_input_scale: float = 0.0
    """m; > 0: the coupling nets see (x - x_ref) / flow_input_scale (weights initialised and explored in
    those units). 0: they see x in m."""
    stiffness: float | None = None
    """N/m: S = stiffness * I in the flow's latent space (None: gear 4, peg 1, block 1)."""
    stiffness_axial: float | None = None
    """N/m: S entry of the insertion (z) axis, replacing stiffness there (None: isotropic)."""
    damping: float | None = None
    """N s/m: D = damping * I in the latent space (None: 1)."""
    gains: str = "fixed"
    """fixed (S, D as set) | learned (their diagonals through exp: always positive definite)."""
    potential_force_bound: float = 0.0
    """N, latent space: the potential's pull is bounded to this, growing linearly beyond (0: off).
    Parameter exploration only; docs/controller.md."""
    stiffness_floor: float = 0.0
    """N/m: no learned diagonal entry of S below it, in any draw, the mean or a loaded policy (0: off)."""
    sigma_init: float | None = None
    """N: initial std of the action noise (exploration: action) (None: gear 5, peg 1, block 2)."""

    # --- PPO ---------------------------------------------------------------------------------------
    learning_rate: float = 2.5e-4
    """Adam step size (action exploration)."""
    update_epochs: int = 10
    """passes over the batch per update."""
    minibatch_size: int = 64
    """decisions per gradient step (action exploration)."""
    clip_coef: float = 0.2
    """PPO's ratio clip epsilon."""
    gamma: float = 0.99
    """discount per decision."""
    gae_lambda: float = 0.97
    """GAE lambda."""

    # --- exploration -------------------------------------------------------------------------------
    exploration: str = "action"
    """action (force noise, PPO per decision) | params (each rollout a deterministic controller with
    parameters drawn around the policy's; PPO per rollout; docs/learner.md)."""
    param_sigma_gains: float = 0.3
    """params: initial std of ln S and ln D per diagonal entry."""
    param_sigma_flow: float = 0.0
    """params: initial std of the flow's explored coordinates (normalised weights; 0: flow not explored)."""
    param_flow_dim: int = 8
    """params: number of fixed random directions explored in the s/t output layers' weights."""
    param_lr: float = 0.05
    """params: Adam step of the mean, in units of its current std."""
    param_sigma_lr: float = 0.05
    """params: Adam step of the exploration log-stds (0: stds fixed)."""
    param_sigma_decay: float = 1.0
    """params: factor on the stds after every update, in (0, 1]."""
    param_sigma_settle: float = 1.0
    """params: extra factor on the stds after an update that meets param_settle_rule, in (0, 1] (1: off)."""
    param_settle_rule: str = "mean"
    """params: mean (the mean's own rollout, the odd last one, inserted while < 90 % of the draws did) |
    batch (param_settle_from <= batch success < 90 %)."""
    param_settle_from: float = 0.6
    """params, settle rule batch: the batch success rate from which the spread settles."""
    param_elite: str = "none"
    """params: none | minority_returns (a cross-entropy step after PPO's: while some but fewer than half
    of the rollouts insert, the mean moves to their average; while none does, to the best quarter of the
    draws by return if each beat the mean's own rollout). Needs an odd rollouts_per_iter."""
    param_sigma_jump: float = 1.0
    """params: factor on the stds when param_elite moves the mean onto rollouts that inserted (1: off)."""

    # --- run ---------------------------------------------------------------------------------------
    seed: int = 0
    """seed of the policy initialisation and of every random draw of the run."""
    iterations: int = 100
    """PPO iterations, each rollouts_per_iter episodes and one update."""
    rollouts_per_iter: int = 15
    """episodes per iteration."""
    eval_episodes: int = 10
    """episodes of the deterministic controller from held-out starts, before and after training."""
    eval_every: int = 0
    """also evaluate after every eval_every-th iteration (0: only before and after)."""
    init_checkpoint: str = ""
    """a run's checkpoint.pt to start from (its flow, S, D and spread; this run's goal) ('': none)."""
    init_target_kl: float = 0.02
    """with init_checkpoint: an update stops once approx_kl exceeds 1.5 x this (0: never)."""

    @property
    def eval_starts(self) -> int:
        """Episodes of a held-out evaluation: ``eval_episodes``, at most 1 with fixed starts (all alike)."""
        return min(self.eval_episodes, 1) if self.start == "fixed" else self.eval_episodes

    @property
    def update_target_kl(self) -> float:
        """The ``target_kl`` the updates use: ``init_target_kl`` when fine-tuning, else 0 (no early stop)."""
        return self.init_target_kl if self.init_checkpoint else 0.0

    def __post_init__(self) -> None:
        self._coerce_types()
        for name, value in TASK_DEFAULTS[self.task_kind].items():
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
        _choice("flow_init", self.flow_init, FLOW_INITS)
        _choice("gains", self.gains, GAINS)
        _choice("exploration", self.exploration, EXPLORATIONS)
        _choice("param_settle_rule", self.param_settle_rule, SETTLE_RULES)
        _choice("param_elite", self.param_elite, ELITES)
        _positive("param_sigma_gains", self.param_sigma_gains)
        _non_negative("param_sigma_flow", self.param_sigma_flow)
        _int_range("param_flow_dim", self.param_flow_dim, 1, 100_000)
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
        for name in ("param_sigma_decay", "param_sigma_settle", "param_sigma_jump"):
            if not 0.0 < getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in (0, 1], got {getattr(self, name)}")
        if not 0.0 <= self.param_settle_from <= 1.0:
            raise ValueError(f"param_settle_from must be in [0, 1], got {self.param_settle_from}")
        if self.param_sigma_settle < 1.0 and self.param_settle_rule == "mean" and self.rollouts_per_iter % 2 == 0:
            raise ValueError("param_sigma_settle with param_settle_rule mean needs an odd rollouts_per_iter: the "
                             "last rollout runs the mean")
        if self.param_elite != "none" and self.rollouts_per_iter % 2 == 0:
            raise ValueError("param_elite needs an odd rollouts_per_iter: the last rollout runs the mean")
        if self.exploration == "params" and self.gains == "fixed" and self.param_sigma_flow == 0.0:
            raise ValueError("exploration=params needs something to explore: gains=learned or param_sigma_flow > 0")
        _positive("sigma_init", self.sigma_init)
        _positive("episode_seconds", self.episode_seconds)
        _positive("decision_period", self.decision_period)
        _positive("stiffness", self.stiffness)
        _positive("damping", self.damping)
        if self.stiffness_axial is not None:
            _positive("stiffness_axial", self.stiffness_axial)
        _positive("learning_rate", self.learning_rate)
        _non_negative("init_target_kl", self.init_target_kl)
        _int_range("seed", self.seed, 0, 2**32 - 1)
        _int_range("iterations", self.iterations, 1, 1_000_000)
        _int_range("rollouts_per_iter", self.rollouts_per_iter, 1, 100_000)
        _int_range("n_flow", self.n_flow, 1, 64)
        _int_range("n_hidden", self.n_hidden, 1, 1024)
        _int_range("update_epochs", self.update_epochs, 1, 10_000)
        _int_range("minibatch_size", self.minibatch_size, 1, 10_000_000)
        _int_range("eval_episodes", self.eval_episodes, 0, 100_000)
        _int_range("eval_every", self.eval_every, 0, 100_000)
        friction = self.friction_ranges()  # ValueError naming the range
        if friction.randomized and self.start == "fixed":
            raise ValueError("friction_coulomb / friction_viscous are drawn from each episode's start seed; with "
                             "start: fixed there is none (every episode would get the ranges' middles): use "
                             "start: random, or give each range one value ([x, x])")
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

    @property
    def task_kind(self) -> str:
        """The task's kind: ``block``, or its task file's part (``gear``, ``peg``); the built-in task files keep
        their name (``gear_clamp``). Raises ``ValueError`` for a task that is neither a built-in nor a file."""
        if self.task in TASK_DEFAULTS:
            return self.task
        try:
            return load_task(self.task).kind
        except TaskFileError as e:
            raise ValueError(f"task: {e}") from None

    @property
    def held_part(self) -> str:
        """The part in the simulated hand (``Part.text``): the task file's part; the gear for the block task
        (whose scene has no arm)."""
        return "gear" if self.task == "block" else load_task(self.task).part.text()

    def policy_law(self) -> PolicyLaw:
        """The law the policy runs under (force bound, stiffness floor, held part; the gains' defaults):
        it travels with the policy to every controller."""
        return PolicyLaw(potential_force_bound=self.potential_force_bound, stiffness_floor=self.stiffness_floor,
                         held_part=self.held_part)

    def friction_ranges(self) -> FrictionRanges:
        """The per-episode joint friction ranges (``nf_core.friction``; off when both are [0, 0])."""
        return FrictionRanges(tuple(self.friction_coulomb), tuple(self.friction_viscous))

    def stiffness_matrix(self) -> np.ndarray:
        """S: ``stiffness`` on every axis, ``stiffness_axial`` (if set) on the last (insertion) axis."""
        return _diagonal(self.dim, self.stiffness, self.stiffness_axial)

    def damping_matrix(self) -> np.ndarray:
        """D: ``damping`` on every axis."""
        return _diagonal(self.dim, self.damping, None)

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

    def stored(self) -> dict[str, Any]:
        """``to_dict`` as a checkpoint keeps it: with the task file's text (``task_file``) when the task is
        a file, so that the checkpoint still holds its cell where that file is not (another machine)."""
        out = self.to_dict()
        if self.task not in TASK_DEFAULTS:
            out[TASK_FILE_KEY] = task_path(self.task).read_text()
        return out

    @staticmethod
    def with_defaults(stored: dict[str, Any]) -> dict[str, Any]:
        """A stored config (checkpoint, config.json) as today's settings: every setting added since it was
        written filled in by its task's default (what that run used), and every removed setting dropped if
        its value is what the code now always does. ``ValueError`` names a removed mode the run used."""
        used = []
        for name, plain in REMOVED_SETTINGS.items():
            moot = (name.startswith("param_") and stored.get("exploration") != "params") \
                or (name == "param_flow" and not stored.get("param_sigma_flow"))
            if name in stored and plain is not None and stored[name] != plain and not moot:
                used.append(f"{name}={stored[name]!r}")
        if used:
            raise ValueError(f"a run with removed settings ({', '.join(used)}); the last commit that had them is "
                             "named in docs/results/removed_settings.md")
        stored = dict(stored)
        text = stored.pop(TASK_FILE_KEY, None)
        if text is not None and not Path(stored["task"]).is_file():
            stored["task"] = str(materialise_task(text))
        kept = {k: v for k, v in stored.items() if k not in REMOVED_SETTINGS}
        return {**TrainConfig(task=stored["task"]).to_dict(), **kept}

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
        cls, yaml_path: str | Path | list[str | Path] | None = None, overrides: dict[str, Any] | None = None
    ) -> TrainConfig:
        """Defaults < ``yaml_path`` (a task's parameters file, or a list: a task file then its overlays,
        later files win) < ``overrides`` (values or strings)."""
        values: dict[str, Any] = {}
        paths = [] if yaml_path is None else yaml_path if isinstance(yaml_path, list) else [yaml_path]
        for path in paths:
            for key, value in read_yaml_params(path).items():
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


def parse_sets(items: list[str]) -> dict[str, str]:
    """``KEY=VALUE`` strings (a command line's ``--set``) as settings to override; ValueError names a bad one."""
    out: dict[str, str] = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"--set expects KEY=VALUE, got {item!r}")
        out[key.strip()] = value.strip()
    return out


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
