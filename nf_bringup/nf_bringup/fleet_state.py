"""The fleet as the live view shows it, ROS-free: per-arm state built from controller status and
rollout-chunk fields, and the learner's progress read from its run folder. ``fleet_view`` wires
topics to it and serves what it returns as JSON; the tests feed it plain values.
"""

from __future__ import annotations

import json
import math
import os
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

# nf_msgs/ControllerStatus MODE_* constants (repeated here so the core needs no ROS message import)
MODE_NAMES = {0: "idle", 1: "running", 2: "safe_hold", 3: "resetting"}
SUCCESS_WINDOW = 20  # episodes per arm behind its success rate
STALE_AFTER = 2.0  # s without a controller status before an arm shows as not alive


def arm_name(namespace: str) -> str:
    """The arm's name as the learner writes it in arms.json: "/" for the root, else "/a/b"."""
    ns = namespace.strip().strip("/")
    return f"/{ns}" if ns else "/"


def json_safe(value: Any) -> Any:
    """``value`` with NaN and infinities as None (strict JSON: a browser's parser refuses NaN)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


@dataclass
class ArmState:
    """What is known of one arm: its latest status and its last episodes' outcomes."""

    name: str
    mode: int | None = None
    fault: str = ""
    policy_version: int = 0
    episode_id: int = 0
    lyapunov: float = math.nan
    lyapunov_rate: float = math.nan
    torque_norm: float = math.nan
    deadline_misses: int = 0
    status_at: float | None = None  # the caller's clock (s) at the latest status
    episode_time: float = math.nan  # s into the running episode, from its latest rollout chunk
    episodes: int = 0  # finished episodes seen (final chunks)
    last_depth: float = math.nan  # insertion depth at the end of the last episode [m]
    outcomes: deque[bool] = field(default_factory=lambda: deque(maxlen=SUCCESS_WINDOW))

    def as_dict(self, now: float) -> dict[str, Any]:
        """The arm as one JSON object (``now``: the same clock as ``status_at``)."""
        age = None if self.status_at is None else now - self.status_at
        return json_safe({
            "arm": self.name,
            "alive": age is not None and age <= STALE_AFTER,
            "status_age": age,
            "mode": MODE_NAMES.get(self.mode, f"mode {self.mode}") if self.mode is not None else "unknown",
            "fault": self.fault,
            "policy_version": self.policy_version,
            "episode_id": self.episode_id,
            "episode_time": self.episode_time,
            "lyapunov": self.lyapunov,
            "lyapunov_rate": self.lyapunov_rate,
            "torque_norm": self.torque_norm,
            "deadline_misses": self.deadline_misses,
            "episodes": self.episodes,
            "success_rate": sum(self.outcomes) / len(self.outcomes) if self.outcomes else None,
            "success_window": len(self.outcomes),
            "last_success": self.outcomes[-1] if self.outcomes else None,
            "last_depth": self.last_depth,
        })


class FleetState:
    """Every arm seen so far, by name. ``status``/``chunk`` return True when something a viewer
    would notice changed (mode, fault, policy, episode, an episode's end); V alone does not count,
    it changes with every status."""

    def __init__(self, success_depth: float) -> None:
        self.success_depth = success_depth
        self.arms: dict[str, ArmState] = {}

    def arm(self, namespace: str) -> ArmState:
        """The state of the arm in ``namespace`` (made on first use)."""
        name = arm_name(namespace)
        if name not in self.arms:
            self.arms[name] = ArmState(name)
        return self.arms[name]

    def status(self, namespace: str, now: float, *, mode: int, fault: str, policy_version: int, episode_id: int,
               lyapunov: float, lyapunov_rate: float, torque_norm: float, deadline_misses: int) -> bool:
        """A ControllerStatus of the arm in ``namespace``, received at ``now``."""
        arm = self.arm(namespace)
        before = (arm.mode, arm.fault, arm.policy_version, arm.episode_id, arm.status_at is None)
        arm.mode, arm.fault = int(mode), str(fault)
        arm.policy_version, arm.episode_id = int(policy_version), int(episode_id)
        arm.lyapunov, arm.lyapunov_rate = float(lyapunov), float(lyapunov_rate)
        arm.torque_norm, arm.deadline_misses = float(torque_norm), int(deadline_misses)
        arm.status_at = now
        return before != (arm.mode, arm.fault, arm.policy_version, arm.episode_id, False)

    def chunk(self, namespace: str, *, episode_id: int, final: bool, t: Sequence[float],
              insertion_depth: Sequence[float]) -> bool:
        """A RolloutChunk of the arm; its final chunk ends an episode: success when the last sample's
        insertion depth reaches ``success_depth`` (the learner's rule for an episode's end)."""
        arm = self.arm(namespace)
        if len(t):
            arm.episode_time = float(t[-1])
        if not final:
            return False
        depth = float(insertion_depth[-1]) if len(insertion_depth) else math.nan
        arm.last_depth = depth
        arm.outcomes.append(math.isfinite(depth) and depth >= self.success_depth)
        arm.episodes += 1
        arm.episode_id = max(arm.episode_id, int(episode_id))
        return True

    def snapshot(self, now: float) -> dict[str, Any]:
        """Every arm, sorted by name: the ``/fleet/arms`` message."""
        return {"arms": [self.arms[n].as_dict(now) for n in sorted(self.arms)], "count": len(self.arms)}


def learner_dir(path: Path) -> Path | None:
    """The learner's output folder for ``path``: the folder itself when it holds the learner's files
    (``out_dir``), ``path/learner`` (a ``make run`` folder), or the newest run under ``path``
    (``runs``: follows the run being made). None when there is none yet."""
    if (path / "config.json").exists() or (path / "metrics.json").exists():
        return path
    if (path / "learner").is_dir():
        return path / "learner"
    if not path.is_dir():
        return None
    runs = [p / "learner" for p in path.iterdir() if (p / "learner").is_dir()]
    return max(runs, key=lambda p: p.stat().st_mtime) if runs else None


def _read_json(path: Path) -> Any:
    """The file's JSON, or None when absent or half-written (the learner replaces files atomically,
    but a folder may come from elsewhere)."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


class LearnerProgress:
    """The learner's progress from its files (metrics.json, config.json, arms.json), read again only
    when one of them changed."""

    FILES = ("metrics.json", "config.json", "arms.json")

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self._key: tuple[Any, ...] | None = None
        self._message: dict[str, Any] | None = None

    def poll(self) -> tuple[dict[str, Any] | None, bool]:
        """The ``/fleet/learner`` message (None without a run folder) and whether it changed."""
        folder = learner_dir(self.run_dir)
        if folder is None:
            return None, False
        key: tuple[Any, ...] = (str(folder),)
        for name in self.FILES:
            try:
                st = os.stat(folder / name)
                key += (st.st_mtime_ns, st.st_size)
            except OSError:
                key += (None,)
        if key == self._key:
            return self._message, False
        self._key = key
        self._message = progress_message(folder, _read_json(folder / "metrics.json"),
                                         _read_json(folder / "config.json"), _read_json(folder / "arms.json"))
        return self._message, True


def progress_message(folder: Path, metrics: Any, config: Any, arms: Any) -> dict[str, Any]:
    """The learner's progress from its parsed files (any may be None)."""
    rows = metrics if isinstance(metrics, list) else []
    last = rows[-1] if rows and isinstance(rows[-1], dict) else {}
    total = config.get("iterations") if isinstance(config, dict) else None
    walls = [r["wall_seconds"] for r in rows if isinstance(r, dict) and isinstance(r.get("wall_seconds"), float)]
    per_iteration = sum(walls) / len(walls) if walls else None
    iteration = int(last.get("iteration", 0))
    left = None
    if per_iteration is not None and isinstance(total, int):
        left = max(total - iteration, 0) * per_iteration
    return json_safe({
        "run": str(folder),
        "iteration": iteration,
        "iterations": total,
        "success_rate": last.get("success_rate"),
        "return_mean": last.get("return_mean"),
        "final_distance_mean": last.get("final_distance_mean"),
        "seconds_per_iteration": last.get("wall_seconds"),
        "mean_seconds_per_iteration": per_iteration,
        "seconds_left": left,
        "arms_used": last.get("arms_used"),
        "rerun_episodes": last.get("rerun_episodes"),
        "dropped_episodes": last.get("dropped_episodes"),
        "success_history": [r.get("success_rate") for r in rows if isinstance(r, dict)],
        "rollouts_per_arm": arms.get("arms", {}) if isinstance(arms, dict) else {},
    })
