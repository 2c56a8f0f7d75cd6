"""Streamed rollouts to ``EpisodeRecord``: collect ``nf_msgs/RolloutChunk`` messages per episode,
check that none is missing, and build the record the trainer's PPO update takes. ROS-free (works
on any objects with the message's fields), so bags can be re-learned offline with it.
"""

from __future__ import annotations

import threading
from collections import defaultdict
from typing import Any

import numpy as np

from nf_core.reward import REWARD_TERMS

from .rollout import EpisodeRecord


class IncompleteEpisodeError(ValueError):
    """An episode whose chunks are missing, duplicated or inconsistent: it is dropped, never used."""


def _rows(values: Any, dim: int, what: str, n: int) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64)
    if a.size != n * dim:
        raise IncompleteEpisodeError(f"{what}: {a.size} values for {n} samples of dimension {dim}")
    return a.reshape(n, dim)


def episode_from_chunks(chunks: list[Any], *, success_depth: float, final_distance: float | None = None,
                        torque_norm: float = float("nan"), final_success: bool | None = None,
                        start_seed: int | None = None) -> EpisodeRecord:
    """The ``EpisodeRecord`` of one episode from all its chunks (any order).

    Raises ``IncompleteEpisodeError`` when a chunk is missing or duplicated, the final chunk has not
    arrived, or sizes disagree. ``final_distance``/``final_success`` come from the action result
    (the state after the last decision); without them the last streamed sample stands in.
    """
    if not chunks:
        raise IncompleteEpisodeError("no chunks")
    chunks = sorted(chunks, key=lambda c: int(c.seq))
    episode = int(chunks[0].episode_id)
    seqs = [int(c.seq) for c in chunks]
    finals = [c for c in chunks if c.final]
    if not finals:
        raise IncompleteEpisodeError(f"episode {episode}: final chunk missing (have seq {seqs})")
    n_chunks = int(finals[0].n_chunks)
    if seqs != list(range(n_chunks)):
        raise IncompleteEpisodeError(f"episode {episode}: expected chunks 0..{n_chunks - 1}, have seq {seqs}")
    if any(int(c.episode_id) != episode for c in chunks):
        raise IncompleteEpisodeError("chunks of different episodes mixed")
    versions = {int(c.policy_version) for c in chunks}
    if len(versions) != 1:
        raise IncompleteEpisodeError(f"episode {episode}: chunks from policy versions {sorted(versions)}")
    d = int(chunks[0].dim)
    cols: dict[str, list[np.ndarray]] = defaultdict(list)
    for c in chunks:
        n = len(c.t)
        cols["t"].append(np.asarray(c.t, dtype=np.float64))
        for name in ("x", "xdot", "u_mean", "action"):
            cols[name].append(_rows(getattr(c, name), d, name, n))
        for name in ("log_prob", "reward", "insertion_depth"):
            a = np.asarray(getattr(c, name), dtype=np.float64)
            if a.size != n:
                raise IncompleteEpisodeError(f"{name}: {a.size} values for {n} samples")
            cols[name].append(a)
        cols["terms"].append(_rows(c.reward_terms, len(REWARD_TERMS), "reward_terms", n))
    col = {k: np.concatenate(v) for k, v in cols.items()}
    terms = {name: col["terms"][:, i].copy() for i, name in enumerate(REWARD_TERMS)}
    depth = col["insertion_depth"]
    success = np.nan_to_num(depth, nan=0.0) >= success_depth
    if final_success is not None and len(success):
        success[-1] = bool(final_success)
    if final_distance is None:
        final_distance = float("nan")
    return EpisodeRecord(
        t=col["t"], x=col["x"], xdot=col["xdot"], u_mean=col["u_mean"], action=col["action"],
        log_prob=col["log_prob"], reward=col["reward"], terms=terms, depth=np.nan_to_num(depth, nan=0.0),
        success=success, start_seed=start_seed, final_distance=float(final_distance),
        torque_norm=float(torque_norm), info={"episode_id": episode, "policy_version": versions.pop()},
    )


class ChunkCollector:
    """Chunks by episode id, as they arrive (any thread); ``pop`` hands one episode's chunks over."""

    def __init__(self, max_episodes: int = 256) -> None:
        self._by_episode: dict[int, list[Any]] = defaultdict(list)
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)  # notified by every ``add``
        self.max_episodes = max_episodes
        self.received = 0

    def add(self, chunk: Any) -> None:
        """Keep one chunk (the oldest episodes are forgotten beyond ``max_episodes``)."""
        with self._lock:
            self.received += 1
            self._by_episode[int(chunk.episode_id)].append(chunk)
            while len(self._by_episode) > self.max_episodes:
                del self._by_episode[next(iter(self._by_episode))]
            self._arrived.notify_all()

    def count(self, episode_id: int) -> int:
        """Chunks held for ``episode_id``."""
        with self._lock:
            return len(self._by_episode.get(int(episode_id), ()))

    def wait_for(self, episode_id: int, count: int, timeout: float) -> bool:
        """Block until ``count`` chunks of ``episode_id`` are held (True) or ``timeout`` s pass (False)."""
        key = int(episode_id)
        with self._arrived:
            return self._arrived.wait_for(lambda: len(self._by_episode.get(key, ())) >= count, timeout)

    def pop(self, episode_id: int) -> list[Any]:
        """All chunks of ``episode_id`` (removed)."""
        with self._lock:
            return self._by_episode.pop(int(episode_id), [])
