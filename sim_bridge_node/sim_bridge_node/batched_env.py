"""Many environments stepped together, on a few threads (closed loop: one step per call).

Each environment keeps its own ``MjData`` (all share one compiled ``MjModel``, unless joint friction
is randomized per episode: then each has its own copy), so a batch member
behaves bit for bit like a lone ``InsertionEnv`` with the same seed and torques. ``step`` checks
the whole (n_envs, nu) torque array once, clamps it in one vectorised call, then steps the envs
in contiguous chunks: one chunk per worker thread, the first on the calling thread. MuJoCo
releases the GIL inside ``mj_step1``/``mj_step2``, so the chunks run in parallel.

(``mujoco.rollout`` was measured as the alternative, see ``bench/bench_sim.py``: it is built for
open-loop control sequences; stepping it one step at a time re-copies the full state in and out
every call and drops the solver warm start, and its per-thread ``MjData`` no longer holds each
environment's derived quantities such as contacts.)
"""

from __future__ import annotations

import copy
import dataclasses
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np

from nf_core.friction import FrictionRanges
from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.scenes import build_scene


class BatchObservation(NamedTuple):
    """Stacked state of all environments (first axis = environment)."""

    q: np.ndarray
    dq: np.ndarray
    x: np.ndarray
    xdot: np.ndarray
    time: np.ndarray


class BatchedEnv:
    """``n_envs`` copies of one task's environment, stepped together on ``n_threads`` threads."""

    def __init__(self, task: str = "gear", n_envs: int = 8, n_threads: int = 2, *, plane: str = "vertical",
                 start_std: float | np.ndarray | None = None, friction: FrictionRanges | None = None):
        """Compile the scene once and create ``n_envs`` environments sharing the model; with
        ``friction`` ranges on (joint friction drawn per episode from its seed, as a lone
        ``InsertionEnv`` with ``set_friction_ranges`` does) each gets its own copy of the model."""
        if n_envs < 1 or n_threads < 1:
            raise ValueError(f"n_envs and n_threads must be >= 1, got {n_envs}, {n_threads}")
        scene = build_scene(task, plane=plane)
        # per-episode friction and cell variations live in the model
        own = (friction is not None and friction.enabled) or (scene.spec is not None and scene.spec.randomise.enabled)
        self.envs = [InsertionEnv(scene=dataclasses.replace(scene, model=copy.copy(scene.model)) if own else scene,
                                  start_std=start_std) for _ in range(n_envs)]
        if own:
            for env in self.envs:
                env.set_friction_ranges(friction)
        self.task = scene.task
        self.n_threads = min(n_threads, n_envs)
        self._chunks = [list(c) for c in np.array_split(np.arange(n_envs), self.n_threads)]
        self._pool = ThreadPoolExecutor(self.n_threads - 1) if self.n_threads > 1 else None
        self._lo = self.envs[0]._ctrl_lo
        self._hi = self.envs[0]._ctrl_hi
        self._clamped = np.zeros((n_envs, self.nu))

    @property
    def n_envs(self) -> int:
        """Number of environments."""
        return len(self.envs)

    @property
    def nu(self) -> int:
        """Actuators per environment."""
        return self.envs[0].nu

    def close(self) -> None:
        """Stop the worker threads."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> BatchedEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def reset(self, seeds: list[int | None] | np.ndarray | None = None) -> BatchObservation:
        """Reset every environment; ``seeds[i]`` as in ``InsertionEnv.reset`` (None: all fixed)."""
        if seeds is None:
            seeds = [None] * self.n_envs
        if len(seeds) != self.n_envs:
            raise ValueError(f"need {self.n_envs} seeds, got {len(seeds)}")
        for env, seed in zip(self.envs, seeds, strict=True):
            env.reset(None if seed is None else int(seed))
        return self.observation()

    def step(self, tau: np.ndarray) -> None:
        """One 1 ms step of every environment with ``tau[i]``; ``ValueError`` (nothing stepped)
        if the array is not (n_envs, nu) or holds NaN/Inf."""
        try:
            arr = np.asarray(tau, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"torque batch must be a numeric ({self.n_envs}, {self.nu}) array: {exc}") from None
        if arr.shape != (self.n_envs, self.nu):
            raise ValueError(f"torque batch must have shape ({self.n_envs}, {self.nu}), got {arr.shape}")
        finite = np.isfinite(arr)
        if not finite.all():
            bad = sorted({int(i) for i in np.argwhere(~finite)[:, 0]})
            raise ValueError(f"torque batch contains NaN or Inf for environments {bad}")
        np.clip(arr, self._lo, self._hi, out=self._clamped)
        if self._pool is None:
            self._run_chunk(self._chunks[0])
            return
        futures = [self._pool.submit(self._run_chunk, chunk) for chunk in self._chunks[1:]]
        self._run_chunk(self._chunks[0])
        for f in futures:
            f.result()

    def _run_chunk(self, indices: list[int]) -> None:
        envs, clamped = self.envs, self._clamped
        for i in indices:
            env = envs[i]
            env.last_torque[:] = clamped[i]
            env._step_clamped()

    def observation(self) -> BatchObservation:
        """Stacked joint and task-space state."""
        return BatchObservation(self.q, self.dq, self.x, self.xdot, self.time)

    @property
    def q(self) -> np.ndarray:
        """Joint positions, (n_envs, nq)."""
        return np.stack([e.q for e in self.envs])

    @property
    def dq(self) -> np.ndarray:
        """Joint velocities, (n_envs, nq)."""
        return np.stack([e.dq for e in self.envs])

    @property
    def x(self) -> np.ndarray:
        """TCP positions (world), (n_envs, 3)."""
        return np.stack([e.x for e in self.envs])

    @property
    def xdot(self) -> np.ndarray:
        """TCP velocities (world), (n_envs, 3)."""
        return np.stack([e.xdot for e in self.envs])

    @property
    def time(self) -> np.ndarray:
        """Simulated time of each environment (s)."""
        return np.array([e.time for e in self.envs])

    @property
    def insertion_depth(self) -> np.ndarray:
        """Insertion depth of each environment (m)."""
        return np.array([e.insertion_depth for e in self.envs])

    @property
    def success(self) -> np.ndarray:
        """Success flag of each environment."""
        return np.array([e.success for e in self.envs])

    @property
    def contact_force(self) -> np.ndarray:
        """Net contact force on each held part (N, world), (n_envs, 3)."""
        return np.stack([e.contact_force for e in self.envs])

    @property
    def goal_position(self) -> np.ndarray:
        """The goal TCP position (same for all environments)."""
        return self.envs[0].goal_position
