"""In-process training of the NF (or MLP) policy: the loop, metrics, evaluations and checkpoints.

One iteration: ``rollouts_per_iter`` episodes (compiled evaluator in the 1 kHz loop), one update by
the run's exploration kind (``action_ppo.ActionNoisePPO`` or ``param_ppo.ParamSpacePPO``), a metrics
row and a checkpoint. All randomness after the policy initialisation comes from one numpy Generator seeded
once with ``cfg.seed`` (training start seeds, noise seeds, minibatch order); its state is in the
checkpoint, so a restarted run continues exactly as an uninterrupted one.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import logging
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from nf_controller_node.flow_eval import FlowEvaluator
from nf_core.flow_spec import FlowArchitecture
from nf_core.policy_params import PolicyParameters
from nf_core.reward import REWARD_TERMS

from .action_ppo import ActionNoisePPO
from .config import FLOW_ACTIVATION, MLP_ACTIVATION, MLP_HIDDEN, TrainConfig
from .flow import init_flow_weights, move_flow_to_goal, rescale_flow_weights
from .mlp_policy import MLPEvaluator, MLPPolicy
from .param_explore import ParamExploration
from .param_ppo import ParamSpacePPO
from .policy import NFPolicy
from .rollout import EpisodeRecord, RolloutRunner

LOG = logging.getLogger("learner_node.trainer")
CHECKPOINT = "checkpoint.pt"
EVALUATION_FILE = "evaluation.json"  # the deterministic controller on the held-out starts after training
PRIOR_EVALUATION_FILE = "evaluation_prior.json"  # the same before iteration 1
CHECKPOINT_FORMAT = 1
EVAL_SEED_BASE = 1_000_000_000  # held-out evaluation starts: seeds >= this; training seeds are below
# (with friction_coulomb / friction_viscous set, they draw their joint friction from the same ranges)
# settings that may differ between a checkpoint and the run that resumes it (init_checkpoint is
# read only by a run's start: a resumed run continues from its own checkpoint whatever it says)
RESUMABLE_CHANGES = frozenset({"iterations", "eval_episodes", "eval_every", "init_checkpoint", "init_target_kl"})
PERIODIC_EVALUATIONS = "evaluations"  # run-folder subdirectory of the eval_every evaluations
# metrics columns of a periodic evaluation <- the evaluation's own keys
EVAL_COLUMNS = {"eval_return": "return_mean", "eval_success": "success_rate",
                "eval_final_distance": "final_distance_mean"}
# the settings that shape a policy's parameters, per policy type (with the task's dimension)
ARCHITECTURE = {"nf": ("n_flow", "n_hidden"), "mlp": ()}
# settings only the NF policy reads: an MLP run's checkpoint resumes whatever they are
NF_ONLY = frozenset({"n_flow", "n_hidden", "flow_init", "stiffness", "damping", "stiffness_axial", "gains",
                     "exploration", "potential_force_bound", "stiffness_floor", "flow_input_scale",
                     "param_sigma_gains", "param_sigma_flow", "param_flow_dim", "param_lr", "param_sigma_lr",
                     "param_sigma_decay", "param_sigma_settle", "param_settle_rule", "param_settle_from",
                     "param_elite", "param_sigma_jump"})
TIMING_KEYS = ("rollout_seconds", "update_seconds", "wall_seconds")


def build_policy(cfg: TrainConfig, x_ref: np.ndarray) -> NFPolicy | MLPPolicy:
    """The policy of ``cfg`` (initialised from ``cfg.seed``) with goal ``x_ref``."""
    d = cfg.dim
    if cfg.policy == "nf":
        arch = FlowArchitecture(dim=d, n_flow=cfg.n_flow, n_hidden=cfg.n_hidden, activation=FLOW_ACTIVATION)
        weights = None
        if cfg.flow_input_scale > 0.0:  # initialised in normalised units: O(1) features over the scale
            normalised = init_flow_weights(arch, np.random.default_rng(cfg.seed), init=cfg.flow_init)
            weights = rescale_flow_weights(arch, normalised, x_ref, cfg.flow_input_scale)
        return NFPolicy(arch, weights=weights, stiffness=cfg.stiffness_matrix(), damping=cfg.damping_matrix(),
                        x_ref=x_ref, sigma_init=cfg.sigma_init, seed=cfg.seed,
                        flow_init=cfg.flow_init, learn_gains=cfg.gains == "learned",
                        stiffness_floor=cfg.stiffness_floor, law=cfg.policy_law())
    return MLPPolicy(d, MLP_HIDDEN, MLP_ACTIVATION, x_ref=x_ref, sigma_init=cfg.sigma_init, seed=cfg.seed)


def read_checkpoint(path: str | Path, what: str = "checkpoint") -> dict[str, Any]:
    """The contents of a checkpoint file; ``ValueError`` naming it (as ``what``) if it is missing, not a
    checkpoint or of another format."""
    path = Path(path)
    if not path.exists():
        raise ValueError(f"{what} {path}: no such file")
    if not path.is_file():
        raise ValueError(f"{what} {path} is not a file (give the run's {CHECKPOINT})")
    try:
        state = torch.load(path, weights_only=True)
    except Exception as exc:  # torch, zip and pickle errors alike: not a checkpoint we wrote
        raise ValueError(f"{what} {path} is not a readable checkpoint: {exc}") from None
    if not isinstance(state, dict) or state.get("format") != CHECKPOINT_FORMAT:
        found = state.get("format") if isinstance(state, dict) else type(state).__name__
        raise ValueError(f"{what} {path}: checkpoint format {found!r}, expected {CHECKPOINT_FORMAT}")
    return state


def architecture_differences(mine: TrainConfig, theirs: TrainConfig) -> list[str]:
    """How the policy ``theirs`` (a checkpoint's settings) describes differs in shape from ``mine``:
    policy type, task dimension and ``ARCHITECTURE``; empty if its parameters fit."""
    if theirs.policy != mine.policy:
        return [f"policy: checkpoint {theirs.policy!r} vs now {mine.policy!r}"]
    out = []
    if theirs.dim != mine.dim:
        out.append(f"dimension: checkpoint {theirs.dim} (task {theirs.task}) vs now {mine.dim} (task {mine.task})")
    out += [f"{k}: checkpoint {getattr(theirs, k)!r} vs now {getattr(mine, k)!r}"
            for k in ARCHITECTURE[mine.policy] if getattr(theirs, k) != getattr(mine, k)]
    return out


def make_evaluator(policy: NFPolicy | MLPPolicy) -> FlowEvaluator | MLPEvaluator:
    """Compiled float64 snapshot of the policy's mean force, for the 1 kHz loop."""
    if isinstance(policy, NFPolicy):
        return FlowEvaluator(policy.to_params())
    return MLPEvaluator.from_policy(policy)


def policy_sigma(policy: NFPolicy | MLPPolicy) -> np.ndarray:
    """Noise std per action dimension, float64 (d,)."""
    with torch.no_grad():
        std = policy.std().to(torch.float64).cpu().numpy()
    return np.broadcast_to(std, (policy.x_ref.shape[0],)).copy()


def episode_summary(episodes: list[EpisodeRecord]) -> dict[str, float]:
    """Means (and some stds) over episodes: return, success, final distance, torque, depth, reward terms."""
    returns = np.array([e.episode_return for e in episodes])
    dist = np.array([e.final_distance for e in episodes])
    out = {
        "return_mean": float(returns.mean()),
        "return_std": float(returns.std()),
        "success_rate": float(np.mean([e.final_success for e in episodes])),
        "final_distance_mean": float(dist.mean()),
        "final_distance_std": float(dist.std()),
        "torque_norm_mean": float(np.mean([e.torque_norm for e in episodes])),
        "max_depth_mean": float(np.mean([e.depth.max() for e in episodes])),
        "faults": float(sum(e.faults for e in episodes)),
    }
    for name in REWARD_TERMS:
        out[f"term_{name}"] = float(np.mean([e.terms[name].sum() for e in episodes]))
    out.update(friction_summary(episodes))
    return out


def friction_summary(episodes: list[EpisodeRecord]) -> dict[str, float]:
    """Joint friction randomized per episode (``TrainConfig.friction_coulomb``/``friction_viscous``):
    the mean over episodes and joints of the drawn Coulomb (Nm) and added viscous (Nm s/rad) friction
    (``friction_coulomb_mean``, ``friction_viscous_mean``); nothing when off (the columns stay as they were)."""
    drawn = [e.info for e in episodes if "friction_coulomb" in e.info]
    if not drawn:
        return {}
    return {"friction_coulomb_mean": float(np.mean([np.mean(i["friction_coulomb"]) for i in drawn])),
            "friction_viscous_mean": float(np.mean([np.mean(i["friction_viscous"]) for i in drawn]))}


def episode_friction(record: EpisodeRecord) -> dict[str, float]:
    """One episode's drawn joint friction for an evaluation's ``per_episode`` row (means over the
    joints); {} when friction is not randomized."""
    return {f"{k}_mean": float(np.mean(record.info[k])) for k in ("friction_coulomb", "friction_viscous")
            if k in record.info}


class Trainer:
    """NF-PPO / MLP-PPO on one task, in process. ``run()`` trains to ``cfg.iterations`` and evaluates."""

    def __init__(self, cfg: TrainConfig, out_dir: str | Path | None = None, progress: bool = False) -> None:
        torch.set_num_threads(1)  # small tensors; extra threads only spin on the shared machines
        self.cfg = cfg
        self.out_dir = Path(out_dir) if out_dir is not None else None
        self.progress = progress
        self.runner = RolloutRunner(cfg)
        self.x_ref = self.runner.x_ref
        self.policy = build_policy(cfg, self.x_ref)
        # init_checkpoint: the checkpoint this run's policy came from (path, its iteration, task, x_ref)
        self.started_from: dict[str, Any] | None = None
        self.update_rule: ActionNoisePPO | ParamSpacePPO = self._make_update_rule()
        self.rng = np.random.default_rng(cfg.seed)
        self.iteration = 0  # completed iterations
        self.history: list[dict[str, float]] = []
        self._evaluated: tuple[int, dict[str, Any]] | None = None  # the last periodic evaluation

    def _make_update_rule(self) -> ActionNoisePPO | ParamSpacePPO:
        """The exploration kind's update, around the policy as it is now."""
        if self.cfg.policy == "nf" and self.cfg.exploration == "params":
            return ParamSpacePPO(self.cfg, self.policy)
        return ActionNoisePPO(self.cfg, self.policy, self.x_ref)

    @property
    def explorer(self) -> ParamExploration | None:
        """The parameter exploration's distribution (None with action noise)."""
        return self.update_rule.explorer if isinstance(self.update_rule, ParamSpacePPO) else None

    @property
    def optimizer(self) -> torch.optim.Optimizer:
        """The update's optimiser."""
        return self.update_rule.optimizer

    # ------------------------------------------------------------------ one iteration
    def episode_seeds(self) -> list[tuple[int, int]]:
        """(start seed, noise seed) of each rollout of the next iteration, from the run's generator.

        The ROS learner draws its episodes' seeds here too, so a run over ROS sees the same
        starts and the same noise as an in-process run with the same config.
        """
        seeds = self.rng.integers(0, EVAL_SEED_BASE, size=(self.cfg.rollouts_per_iter, 2))
        return [(int(start), int(noise)) for start, noise in seeds]

    def episode_plan(self) -> list[tuple[int, int, PolicyParameters | None]]:
        """(start seed, noise seed, controller parameters) of each rollout of the next iteration.

        Action exploration: ``episode_seeds()`` with parameters None (the policy's, with noise). Parameter
        exploration: mirrored pairs of parameter draws sharing a start (the second of a pair reuses the
        first's start seed), each run as a deterministic controller (no noise); the draws are kept for
        ``update``. Over ROS: publish each rollout's parameters before its episode and run it noise-free.
        """
        return self.update_rule.plan(self.episode_seeds(), self.rng)

    def collect(self) -> list[EpisodeRecord]:
        """``rollouts_per_iter`` episodes of the current stochastic policy (or parameter draws)."""
        plan = self.episode_plan()
        if self.explorer is not None:
            return [self.runner.run_episode(FlowEvaluator(params), None, start, None) for start, _, params in plan]
        evaluator = make_evaluator(self.policy)
        sigma = policy_sigma(self.policy)
        return [self.runner.run_episode(evaluator, sigma, start, np.random.default_rng(noise))
                for start, noise, _ in plan]

    def train_iteration(self) -> dict[str, float]:
        """Collect, update, record one metrics row (returned and appended to ``history``)."""
        t0 = time.perf_counter()
        episodes = self.collect()
        return self.update(episodes, time.perf_counter() - t0)

    def update(self, episodes: list[EpisodeRecord | None], rollout_seconds: float) -> dict[str, float]:
        """One PPO update from an iteration's episodes (collected here or streamed over ROS) and its
        metrics row (returned and appended to ``history``); ``iteration`` advances by one.

        Parameter exploration: ``episodes`` are those of ``episode_plan()``, in its order, with None for
        one that failed (its pair then does not count)."""
        t1 = time.perf_counter()
        stats, decisions = self.update_rule.update(list(episodes), self.rng)
        episodes = [e for e in episodes if e is not None]
        t2 = time.perf_counter()
        self.iteration += 1
        row: dict[str, float] = {"iteration": float(self.iteration)}
        row.update(episode_summary(episodes))
        row["sigma"] = float(policy_sigma(self.policy).mean())
        row.update(stats)
        row.update(self.gain_metrics())
        row["decisions"] = float(decisions)
        row["rollout_seconds"] = rollout_seconds
        row["update_seconds"] = t2 - t1
        row["wall_seconds"] = rollout_seconds + (t2 - t1)
        if self.cfg.eval_every > 0:  # every row has the columns, so metrics.csv keeps one header
            row.update(dict.fromkeys(EVAL_COLUMNS, math.nan))
        self.history.append(row)
        return row

    def evaluation_due(self) -> bool:
        """Whether the iteration just completed is one of ``eval_every``'s (and evaluations are on)."""
        every = self.cfg.eval_every
        return every > 0 and self.cfg.eval_episodes > 0 and self.iteration > 0 and self.iteration % every == 0

    def record_evaluation(self, result: dict[str, Any]) -> None:
        """Put a periodic evaluation of the current policy into the last metrics row (``EVAL_COLUMNS``) and,
        with an output folder, into ``evaluations/iteration_NNNN.json``."""
        if not self.history:
            raise ValueError("record_evaluation: no iteration to attach the evaluation to")
        row = self.history[-1]
        for column, key in EVAL_COLUMNS.items():
            row[column] = float(result.get(key, math.nan))
        self._evaluated = (self.iteration, result)
        if self.out_dir is not None:
            folder = self.out_dir / PERIODIC_EVALUATIONS
            folder.mkdir(parents=True, exist_ok=True)
            _atomic_write(folder / f"iteration_{self.iteration:04d}.json",
                          json.dumps(result, indent=1, default=_json_float))

    def gain_metrics(self) -> dict[str, float]:
        """NF policy with learned gains or parameter exploration: S and D diagonals (after the update) and
        the exploration stds; nothing otherwise (the metrics keep the columns they always had)."""
        pol = self.policy
        if not isinstance(pol, NFPolicy) or not (pol.learn_gains or self.explorer is not None):
            return {}
        out: dict[str, float] = {}
        with torch.no_grad():
            S, D = pol.gains()
            for i, v in enumerate(torch.diagonal(S).tolist()):
                out[f"stiffness_{i}"] = v
            for i, v in enumerate(torch.diagonal(D).tolist()):
                out[f"damping_{i}"] = v
            if self.explorer is not None:
                if self.explorer.explore_gains:
                    out["param_sigma_gains"] = float(torch.exp(self.explorer.log_sigma_gains).mean())
                if self.explorer.explore_flow:
                    out["param_sigma_flow"] = float(torch.exp(self.explorer.log_sigma_flow)[0])
        return out

    # ------------------------------------------------------------------ evaluation
    def evaluate(self, episodes: int | None = None) -> dict[str, Any]:
        """The deterministic controller (no noise) from held-out start seeds (one episode if starts are fixed)."""
        n = self.cfg.eval_episodes if episodes is None else episodes
        if self.cfg.start == "fixed":
            n = min(n, 1)
        evaluator = make_evaluator(self.policy)
        recs = [self.runner.run_episode(evaluator, None, EVAL_SEED_BASE + k, None) for k in range(n)]
        if not recs:
            return {"episodes": 0}
        out: dict[str, Any] = {"episodes": n, "iteration": self.iteration}
        if self.started_from is not None:
            out["started_from"] = self.started_from
        out.update(episode_summary(recs))
        out["per_episode"] = [
            {"start_seed": r.start_seed, "return": r.episode_return, "success": r.final_success,
             "final_distance": r.final_distance, "max_depth": float(r.depth.max()), "torque_norm": r.torque_norm,
             **episode_friction(r)}
            for r in recs
        ]
        return out

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue exactly: policy, optimiser, baseline, RNG states, iteration, history."""
        return {
            "format": CHECKPOINT_FORMAT,
            "config": self.cfg.stored(),
            "iteration": self.iteration,
            "policy": self.policy.state_dict(),
            **self.update_rule.state_dict(),  # optimizer, and baseline (action noise) or explorer (params)
            "rng": self.rng.bit_generator.state,
            "torch_rng": torch.get_rng_state(),
            "history": self.history,
            "started_from": self.started_from,
            # what decides the torque besides the policy's tensors (deploy_policy sends it with them)
            "law": dataclasses.asdict(self.cfg.policy_law()),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from ``state_dict`` (the config must match except ``RESUMABLE_CHANGES``, and for the
        MLP policy the NF-only settings)."""
        if state.get("format") != CHECKPOINT_FORMAT:
            raise ValueError(f"checkpoint format {state.get('format')!r}, expected {CHECKPOINT_FORMAT}")
        mine, theirs = self.cfg.to_dict(), state["config"]
        theirs = TrainConfig.with_defaults(theirs)  # a setting newer than the checkpoint: its default
        ignored = RESUMABLE_CHANGES | (NF_ONLY if mine["policy"] == "mlp" else frozenset())
        diff = sorted(k for k in mine if k not in ignored and mine[k] != theirs[k])
        if diff:
            detail = ", ".join(f"{k}: checkpoint {theirs[k]!r} vs now {mine[k]!r}" for k in diff)
            raise ValueError(f"checkpoint was written with different settings ({detail})")
        self.policy.load_state_dict(state["policy"])
        self.update_rule.load_state_dict(state)
        self.rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        self.iteration = int(state["iteration"])
        self.history = [dict(r) for r in state["history"]]
        self.started_from = state.get("started_from")

    def save_checkpoint(self, path: str | Path) -> None:
        """Write the checkpoint atomically (temporary file, then rename)."""
        path = Path(path)
        tmp = path.with_suffix(path.suffix + ".tmp")
        torch.save(self.state_dict(), tmp)
        os.replace(tmp, path)

    def load_checkpoint(self, path: str | Path) -> None:
        """Resume from a checkpoint file."""
        self.load_state_dict(torch.load(Path(path), weights_only=True))

    def init_from_checkpoint(self, path: str | Path) -> str:
        """Start this new run from another run's policy (``TrainConfig.init_checkpoint``): its flow
        weights, S, D and exploration spread; x_ref stays this run's goal, and the iteration counter,
        optimiser, baseline, random streams and metrics stay fresh. Refuses (``ValueError``) a missing
        file and a policy of another architecture; returns a line for the log."""
        if self.iteration or self.history:
            raise RuntimeError("init_from_checkpoint starts a new run: this one has iterations already")
        state = read_checkpoint(path, "init_checkpoint")
        try:
            theirs = TrainConfig(**TrainConfig.with_defaults(state["config"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"init_checkpoint {path}: its settings are unreadable ({exc})") from None
        diff = architecture_differences(self.cfg, theirs)
        if diff:
            raise ValueError(f"init_checkpoint {path} holds a policy of another architecture than this config's "
                             f"({'; '.join(diff)}): start from a checkpoint of this architecture or use its settings")
        source = build_policy(theirs, np.zeros(theirs.dim))
        try:
            source.load_state_dict(state["policy"])
        except (KeyError, RuntimeError) as exc:
            raise ValueError(f"init_checkpoint {path}: its policy does not match its own settings ({exc})") from None
        self._load_policy(source, path, theirs.flow_input_scale)
        if self.explorer is None:
            self.update_rule = self._make_update_rule()  # an optimiser for the loaded weights
            spread = [f"action noise std {float(torch.exp(self.policy.log_std.detach()).mean()):.3g} N"]
        else:
            spread = self._continue_spread(state.get("explorer") or {})
        self.started_from = {"checkpoint": str(Path(path).resolve()), "iteration": int(state["iteration"]),
                             "task": theirs.task, "x_ref": [round(v, 6) for v in source.x_ref.tolist()]}
        return (f"starting a new run from {path} (after iteration {state['iteration']} of a {theirs.task} "
                f"{theirs.policy}-PPO run): its {'flow, S, D' if theirs.policy == 'nf' else 'weights'} and "
                f"exploration spread ({', '.join(spread)}); x_ref "
                f"{np.round(self.x_ref, 4).tolist()} is this run's goal (the checkpoint's: "
                f"{np.round(source.x_ref.numpy(), 4).tolist()}); iteration counter, optimiser, baseline, random "
                "streams and metrics start fresh")

    def _load_policy(self, source: NFPolicy | MLPPolicy, path: str | Path, their_scale: float) -> None:
        """Copy ``source``'s learned parameters (its run's ``flow_input_scale``: ``their_scale``) into this
        run's policy, whose x_ref stays."""
        pol = self.policy
        if source.log_std.shape != pol.log_std.shape:
            raise ValueError(f"init_checkpoint {path}: log_std of shape {tuple(source.log_std.shape)}, "
                             f"this policy's is {tuple(pol.log_std.shape)}")
        with torch.no_grad():
            if isinstance(pol, NFPolicy) and isinstance(source, NFPolicy):
                S, D = source.gains()  # learned or fixed, as the controller ran them
                if pol.learn_gains and not all(bool(torch.equal(m, torch.diag(torch.diagonal(m)))) for m in (S, D)):
                    raise ValueError(f"init_checkpoint {path}: S or D is not diagonal; gains=learned needs diagonals")
                pol.flow.load_flat(self._moved_flow(source, their_scale))
                pol.S.copy_(S)
                pol.D.copy_(D)
                if pol.learn_gains:
                    pol.ln_s.copy_(torch.log(torch.diagonal(S)))
                    pol.ln_d.copy_(torch.log(torch.diagonal(D)))
                    lifted = pol.raise_to_floor()
                    if lifted:
                        LOG.info("init_checkpoint %s: stiffness %s N/m lifted to stiffness_floor %.0f N/m (entries %s)",
                                 path, np.round(torch.diagonal(S).numpy(), 1).tolist(), self.cfg.stiffness_floor,
                                 lifted)
            elif isinstance(pol, MLPPolicy) and isinstance(source, MLPPolicy):
                pol.layers.load_state_dict(source.layers.state_dict())
            else:
                raise ValueError(f"init_checkpoint {path}: a {type(source).__name__}, this run's policy is a "
                                 f"{type(pol).__name__}")
            pol.log_std.copy_(source.log_std)

    def _moved_flow(self, source: NFPolicy, their_scale: float) -> np.ndarray:
        """``source``'s flow weights for this run's goal. With ``flow_input_scale`` (both runs) the nets
        see ``(x - x_ref) / scale``: the learned landscape belongs to the goal (the shaft), so its
        normalised weights are kept and the physical ones follow the goal (the bias of each net's first
        layer moves). Otherwise the weights are kept as learned, in metres of the base frame."""
        flat = source.flow.to_flat()
        if their_scale > 0.0 and self.cfg.flow_input_scale > 0.0:
            if their_scale != self.cfg.flow_input_scale:  # normalised in theirs, then physical in mine
                flat = rescale_flow_weights(self.policy.flow.arch, rescale_flow_weights(
                    self.policy.flow.arch, flat, source.x_ref.detach().numpy(), their_scale, inverse=True),
                    source.x_ref.detach().numpy(), self.cfg.flow_input_scale)
            flat = move_flow_to_goal(self.policy.flow.arch, flat, source.x_ref.detach().numpy(),
                                     np.asarray(self.x_ref, dtype=float), self.cfg.flow_input_scale)
        return flat

    def _continue_spread(self, stored: dict[str, Any]) -> list[str]:
        """Parameter exploration around the loaded policy, with the checkpoint's stds where it has them
        (``stored``: its explorer's state), and a new optimiser; returns the stds, for the log."""
        self.update_rule = self._make_update_rule()  # centred on the loaded flow and gains, in this run's units
        assert self.explorer is not None
        out = []
        basis = stored.get("flow_basis")
        if basis is not None and basis.shape[0] == self.policy.arch.n_params and self.cfg.param_sigma_flow > 0.0:
            # the checkpoint explores its flow along its own directions (fit_demos: the demonstrations')
            self.explorer.use_basis(basis)
            out.append(f"the flow along the checkpoint's {basis.shape[1]} directions")
        with torch.no_grad():
            for name, label in (("log_sigma_gains", "ln S, ln D"), ("log_sigma_flow", "flow")):
                mine = getattr(self.explorer, name)
                if not mine.numel():
                    continue
                theirs = stored.get(name)
                kept = theirs is not None and tuple(theirs.shape) == tuple(mine.shape)
                if kept:
                    mine.copy_(theirs)
                whose = "the checkpoint's" if kept else "this config's: the checkpoint has none"
                out.append(f"{label} std {float(torch.exp(mine).mean()):.3g} ({whose})")
        self.update_rule.restart_optimizer()  # its steps follow the stds
        return out

    def resume_or_init(self, fresh: bool = False) -> str | None:
        """How a run starts: from the run folder's own checkpoint if it has one (unless ``fresh``), else from
        ``cfg.init_checkpoint`` if set, else as initialised. Returns a line for the log (None: the last)."""
        own = None if self.out_dir is None else self.out_dir / CHECKPOINT
        if own is not None and own.exists() and not fresh:
            try:
                self.load_checkpoint(own)
            except ValueError as exc:
                raise ValueError(f"cannot resume from {own}: {exc}") from None
            note = f"resuming from {own} after iteration {self.iteration}"
            if self.started_from is not None:
                note += f" (the run started from {self.started_from['checkpoint']})"
            if self.cfg.init_checkpoint:
                note += (f"; init_checkpoint {self.cfg.init_checkpoint} is not read: the run folder's own "
                         "checkpoint wins")
            return note
        stale = self.clear_results() if fresh else []
        note = f"--fresh: removed the earlier run's {', '.join(stale)}" if stale else None
        if self.cfg.init_checkpoint:
            started = self.init_from_checkpoint(self.cfg.init_checkpoint)
            return f"{note}; {started}" if note else started
        return note

    def clear_results(self) -> list[str]:
        """Remove an earlier run's results from the output folder (metrics, evaluations, checkpoint), so a
        fresh run's folder holds only its own (its evaluations would otherwise sit beside the old ones:
        an old prior's evaluation is not redone). Returns the names removed."""
        if self.out_dir is None or not self.out_dir.is_dir():
            return []
        removed = []
        for name in (CHECKPOINT, "metrics.csv", "metrics.json", PRIOR_EVALUATION_FILE, EVALUATION_FILE):
            if (self.out_dir / name).exists():
                (self.out_dir / name).unlink()
                removed.append(name)
        folder = self.out_dir / PERIODIC_EVALUATIONS
        if folder.is_dir():
            for path in folder.glob("iteration_*.json"):
                path.unlink()
            removed.append(f"{PERIODIC_EVALUATIONS}/")
        return removed

    # ------------------------------------------------------------------ the run
    def write_metrics(self) -> None:
        """``metrics.csv`` and ``metrics.json`` in the output directory (rewritten from the history)."""
        if self.out_dir is None or not self.history:
            return
        keys = list(dict.fromkeys(k for row in self.history for k in row))  # a resumed run may add columns
        _atomic_write(self.out_dir / "metrics.json", json.dumps(self.history, indent=1, default=_json_float))
        tmp = self.out_dir / "metrics.csv.tmp"
        with tmp.open("w", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=keys, restval="")
            writer.writeheader()
            writer.writerows(self.history)
        os.replace(tmp, self.out_dir / "metrics.csv")

    def run(self, evaluate: bool = True, evaluate_prior: bool = True) -> dict[str, Any] | None:
        """Train until ``cfg.iterations`` (metrics and a checkpoint after every iteration), then evaluate.
        With ``evaluate`` and ``evaluate_prior``, a run that starts at iteration 0 with an output folder
        first evaluates the untrained policy on the same held-out starts (``PRIOR_EVALUATION_FILE``),
        as the learner node does over ROS; it changes nothing in the training that follows."""
        if self.out_dir is not None:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            _atomic_write(self.out_dir / "config.json", json.dumps(self.cfg.to_dict(), indent=1))
        LOG.info("training %s-PPO on %s, iterations %d..%d\n%s", self.cfg.policy, self.cfg.task,
                 self.iteration + 1, self.cfg.iterations, self.cfg.table())
        if evaluate and evaluate_prior and self.cfg.eval_episodes and self.iteration == 0 \
                and self.out_dir is not None and not (self.out_dir / PRIOR_EVALUATION_FILE).exists():
            prior = self.evaluate()
            LOG.info("the prior%s (deterministic, %d held-out starts): success %.2f, return %.1f, final distance "
                     "%.4f m", prior_origin(self.started_from), prior["episodes"], prior["success_rate"],
                     prior["return_mean"], prior["final_distance_mean"])
            _atomic_write(self.out_dir / PRIOR_EVALUATION_FILE, json.dumps(prior, indent=1, default=_json_float))
        bar = tqdm(total=self.cfg.iterations, initial=self.iteration, disable=not self.progress,
                   desc=f"{self.cfg.policy}/{self.cfg.task}", unit="it")
        try:
            while self.iteration < self.cfg.iterations:
                row = self.train_iteration()
                if self.evaluation_due():
                    result = self.evaluate()
                    self.record_evaluation(result)
                    LOG.info("iteration %d: deterministic on %d held-out starts: success %.2f, final distance "
                             "%.4f m", self.iteration, result["episodes"], result["success_rate"],
                             result["final_distance_mean"])
                if self.out_dir is not None:
                    self.write_metrics()
                    self.save_checkpoint(self.out_dir / CHECKPOINT)
                bar.update(1)
                bar.set_postfix(ret=f"{row['return_mean']:.0f}", succ=f"{row['success_rate']:.2f}",
                                dist=f"{row['final_distance_mean']:.3f}", kl=f"{row['approx_kl']:.1e}")
                LOG.debug("iteration %d: %s", self.iteration, row)
        finally:
            bar.close()
        if not evaluate or self.cfg.eval_episodes == 0:
            return None
        result = self.evaluate() if self._evaluated is None or self._evaluated[0] != self.iteration \
            else self._evaluated[1]  # eval_every's of the last iteration: the same policy and starts
        LOG.info("evaluation (deterministic, %d held-out starts): success %.2f, return %.1f, final distance %.4f m",
                 result["episodes"], result["success_rate"], result["return_mean"], result["final_distance_mean"])
        if self.out_dir is not None:
            _atomic_write(self.out_dir / EVALUATION_FILE, json.dumps(result, indent=1, default=_json_float))
        return result


def run_evaluations(run_dir: Path) -> list[tuple[str, dict[str, Any]]]:
    """(label, evaluation) of the deterministic evaluations in a run folder: the prior's (before
    iteration 1) and the learned controller's, those that exist."""
    out = []
    for name in (PRIOR_EVALUATION_FILE, EVALUATION_FILE):
        if (run_dir / name).exists():
            e = json.loads((run_dir / name).read_text())
            out.append((f"the prior{prior_origin(e.get('started_from'))} (before iteration 1)"
                        if name == PRIOR_EVALUATION_FILE else f"learned (after iteration {e['iteration']})", e))
    return out


def prior_origin(started_from: dict[str, Any] | None) -> str:
    """", started from <checkpoint>" for a run that began from another run's policy, else ""."""
    return "" if not started_from else f", started from {started_from['checkpoint']}"


def _json_float(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def metrics_without_timing(row: dict[str, float]) -> dict[str, float]:
    """A metrics row without the wall-clock entries (what must repeat exactly across runs)."""
    return {k: v for k, v in row.items() if k not in TIMING_KEYS and not (isinstance(v, float) and math.isnan(v))}
