"""Offline use of a bag, without ROS: decoded messages, the rollouts grouped by episode (and as the
learner's ``EpisodeRecord``), joint trajectories, an episode summary and a plot of a run.

Messages are decoded from the schema stored in the bag (``mcap_ros2``), so a bag opens on any
machine with Python, no ROS install and no ``nf_msgs`` build needed. The decoded objects have the
message's fields as attributes (``msg.header.stamp.sec``, ``chunk.reward``).

A bag of many arms (``run_stack --arms N``) holds each arm's topics under its namespace
(``/arm0/rollouts``, ..): ``arms`` lists them, ``arm_rollout_chunks`` groups rollouts by (arm,
episode id), since two arms number their episodes independently and their ids collide.
"""

from __future__ import annotations

import dataclasses
import sys
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from mcap_ros2.decoder import DecoderFactory

from .bagfile import RawMessage, iter_raw
from .topics import (  # noqa: F401  (the topic names are part of the reader's interface)
    ARM_TOPICS,
    COMMANDS,
    CONTROLLER_STATUS,
    JOINT_STATES,
    POLICY,
    ROLLOUTS,
    TASK_STATUS,
    arm_of,
    arm_topic,
    arms_of,
)


@dataclass(frozen=True)
class Decoded:
    """A decoded message with its recording times."""

    topic: str
    log_time: int  # ns since epoch (receive time)
    msg: Any
    raw: RawMessage


class Decoder:
    """CDR -> message objects from the schemas in the bag (one decoder per schema)."""

    def __init__(self) -> None:
        self._by_schema: dict[tuple[str, str, str, bytes], Any] = {}

    def __call__(self, raw: RawMessage) -> Any:
        schema = raw.schema
        if schema is None:
            raise ValueError(f"cannot decode {raw.topic}: its channel names no schema (or the schema record is lost)")
        key = (raw.channel.message_encoding, schema.encoding, schema.name, schema.data)
        fn = self._by_schema.get(key)
        if fn is None:
            # a factory per schema: DecoderFactory caches by schema id, and ids restart in every file
            fn = DecoderFactory().decoder_for(raw.channel.message_encoding, schema)
            if fn is None:
                raise ValueError(f"cannot decode {raw.topic}: message encoding {raw.channel.message_encoding!r} with "
                                 f"schema encoding {schema.encoding!r} (readable: message encoding 'cdr' with "
                                 f"schema encoding 'ros2msg')")
            self._by_schema[key] = fn
        return fn(raw.data)


def read_messages(bag: str | Path, topics: Any = None) -> Iterator[Decoded]:
    """Decoded messages of ``bag`` in recording order (optionally only ``topics``, absolute names)."""
    decode = Decoder()
    for raw in iter_raw(bag, topics):
        yield Decoded(raw.topic, raw.log_time, decode(raw), raw)


def stamp_ns(header: Any) -> int:
    """A header's stamp in ns."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def as_plain(msg: Any) -> Any:
    """A message from any decoder (rclpy, mcap_ros2, rosbags) as nested dicts, lists and scalars."""
    if isinstance(msg, (bool, int, float, str)) or msg is None:
        return msg
    if isinstance(msg, (bytes, bytearray)):
        return list(msg)
    if isinstance(msg, np.ndarray):
        return msg.tolist()
    if isinstance(msg, np.generic):
        return msg.item()
    if isinstance(msg, (list, tuple)) or type(msg).__name__ == "array":
        return [as_plain(v) for v in msg]
    if hasattr(msg, "get_fields_and_field_types"):  # rclpy: a `byte` is bytes of length 1
        return {name: msg_byte(getattr(msg, name)) if kind == "octet" else as_plain(getattr(msg, name))
                for name, kind in msg.get_fields_and_field_types().items()}
    if dataclasses.is_dataclass(msg):  # rosbags (constants and __msgtype__ are class variables)
        names = [f.name for f in dataclasses.fields(msg) if "ClassVar" not in str(f.type)]
    else:  # mcap_ros2 (SimpleNamespace subclasses with the fields as __slots__)
        names = list(getattr(type(msg), "__slots__", None) or vars(msg))
    return {name: as_plain(getattr(msg, name)) for name in names}


def msg_byte(value: Any) -> int:
    """rclpy's value of a ``byte`` field (bytes of length 1) as an int."""
    return value[0] if isinstance(value, (bytes, bytearray)) else int(value)


def same(a: Any, b: Any) -> bool:
    """Equality of ``as_plain`` values, NaN equal to NaN (numbers compared exactly otherwise)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float) and a != a and b != b:
        return True
    return a == b


# ---------------------------------------------------------------------- rollouts
def arms(bag: str | Path) -> list[str]:
    """The arms recorded in ``bag`` (namespaces, "/" for an arm without one), from its topic names."""
    from .bagfile import scan

    return arms_of(scan(bag).counts)


def rollout_chunks(bag: str | Path, topic: str = ROLLOUTS) -> dict[int, list[Any]]:
    """The RolloutChunk messages of one arm's ``topic`` (``arm_topic(arm, ROLLOUTS)``) grouped by episode
    id (in order of the episodes' first chunk); ``arm_rollout_chunks`` for every arm of a bag."""
    episodes: dict[int, list[Any]] = defaultdict(list)
    for d in read_messages(bag, [topic]):
        episodes[int(d.msg.episode_id)].append(d.msg)
    return dict(episodes)


def arm_rollout_chunks(bag: str | Path) -> dict[tuple[str, int], list[Any]]:
    """Every arm's RolloutChunk messages grouped by (arm namespace, episode id), in order of the
    episodes' first chunk: arms number their episodes independently, so an id alone is ambiguous."""
    topics = {arm_topic(a, ROLLOUTS): a for a in arms(bag)}
    episodes: dict[tuple[str, int], list[Any]] = defaultdict(list)
    for d in read_messages(bag, list(topics)):
        episodes[(topics[d.topic], int(d.msg.episode_id))].append(d.msg)
    return dict(episodes)


def episode_records(bag: str | Path, success_depth: float | None = None, task: str | None = None) -> list[Any]:
    """The learner's ``EpisodeRecord`` of every episode of every arm in the bag (incomplete ones raise
    ``learner_node.ros_episodes.IncompleteEpisodeError``). ``success_depth`` defaults to the task's."""
    from learner_node.ros_episodes import episode_from_chunks

    if success_depth is None:
        from sim_bridge_node.scenes import build_scene

        success_depth = build_scene(task or recorded_task(bag) or "gear").success_depth
    return [episode_from_chunks(chunks, success_depth=success_depth) for chunks in arm_rollout_chunks(bag).values()]


def recorded_task(bag: str | Path) -> str | None:
    """The task named by the first TaskStatus in the bag, of any arm (None without one)."""
    for d in read_messages(bag, [arm_topic(a, TASK_STATUS) for a in arms(bag)]):
        return str(d.msg.task)
    return None


def policies(bag: str | Path) -> list[Any]:
    """Every PolicyParameters message, in recording order."""
    return [d.msg for d in read_messages(bag, [POLICY])]


# ---------------------------------------------------------------------- trajectories
@dataclass
class JointTrajectory:
    """Joint states by stamp (each stamp once: lockstep resends are dropped)."""

    names: list[str]
    stamp_ns: np.ndarray  # (n,) int64
    q: np.ndarray  # (n, nq) rad
    dq: np.ndarray  # (n, nq) rad/s
    effort: np.ndarray  # (n, nq) Nm applied in the step that led to the state

    @property
    def t(self) -> np.ndarray:
        """Stamps in s."""
        return self.stamp_ns * 1e-9

    def resets(self) -> np.ndarray:
        """Indices of reset states (the sim publishes them with zero velocity and zero effort)."""
        return np.flatnonzero(np.all(self.dq == 0.0, axis=1) & np.all(self.effort == 0.0, axis=1))


def joint_trajectory(bag: str | Path, topic: str = JOINT_STATES) -> JointTrajectory:
    """The recorded joint states, one row per distinct stamp, in stamp order."""
    rows: dict[int, tuple] = {}
    names: list[str] = []
    for d in read_messages(bag, [topic]):
        m = d.msg
        names = names or list(m.name)
        rows.setdefault(stamp_ns(m.header), (list(m.position), list(m.velocity), list(m.effort)))
    stamps = np.array(sorted(rows), dtype=np.int64)
    n = len(names)

    def col(i: int) -> np.ndarray:
        return np.array([rows[s][i] for s in stamps], dtype=np.float64).reshape(len(stamps), n)

    return JointTrajectory(names, stamps, col(0), col(1), col(2))


def commands_by_state(bag: str | Path, topic: str = COMMANDS) -> tuple[dict[int, np.ndarray], int]:
    """Lockstep commands keyed by the stamp of the state they answer (the first answer per state,
    the one a lockstep sim applies), and the number of commands without that label."""
    from nf_core.topics import parse_stamp_label

    out: dict[int, np.ndarray] = {}
    unlabeled = 0
    for d in read_messages(bag, [topic]):
        dims = d.msg.layout.dim
        stamp = parse_stamp_label(dims[0].label) if dims else None
        if stamp is None:
            unlabeled += 1
        elif stamp not in out:
            out[stamp] = np.asarray(d.msg.data, dtype=np.float64)
    return out, unlabeled


def task_status(bag: str | Path) -> dict[str, np.ndarray]:
    """TaskStatus as arrays: t (s), insertion_depth (m), success, contact_force (N), part_position (m)."""
    rows = [d.msg for d in read_messages(bag, [TASK_STATUS])]
    return {
        "t": np.array([stamp_ns(m.header) * 1e-9 for m in rows]),
        "insertion_depth": np.array([m.insertion_depth for m in rows]),
        "success": np.array([bool(m.success) for m in rows]),
        "contact_force": np.array([m.contact_force for m in rows]),
        "part_position": np.array([list(m.part_position) for m in rows]).reshape(len(rows), -1),
    }


# ---------------------------------------------------------------------- evaluation
def summarize(bag: str | Path) -> dict[str, Any]:
    """A run from its bag alone: topics and counts, the arms, simulated time (of the arm without a
    namespace; per arm under ``per_arm``), and per episode its arm, policy version, decisions,
    return, final insertion depth and success."""
    counts: dict[str, int] = defaultdict(int)
    for raw in iter_raw(bag):
        counts[raw.topic] += 1
    out: dict[str, Any] = {"bag": str(bag), "counts": dict(counts), "arms": arms_of(counts)}
    per_arm: dict[str, dict[str, Any]] = {}
    for arm in out["arms"]:
        if counts.get(arm_topic(arm, JOINT_STATES)):
            traj = joint_trajectory(bag, arm_topic(arm, JOINT_STATES))
            per_arm[arm] = {"sim_seconds": float((traj.stamp_ns[-1] - traj.stamp_ns[0]) * 1e-9),
                            "states": len(traj.stamp_ns), "resets": len(traj.resets())}
    if "/" in per_arm:
        out.update(per_arm["/"])
    if set(per_arm) - {"/"}:
        out["per_arm"] = per_arm
    episodes = []
    for (arm, episode_id), chunks in arm_rollout_chunks(bag).items():
        chunks = sorted(chunks, key=lambda c: int(c.seq))
        reward = np.concatenate([np.asarray(c.reward, float) for c in chunks])
        depth = np.concatenate([np.asarray(c.insertion_depth, float) for c in chunks])
        complete = bool(chunks[-1].final) and [int(c.seq) for c in chunks] == list(range(int(chunks[-1].n_chunks)))
        episodes.append({"arm": arm, "episode_id": episode_id, "policy_version": int(chunks[0].policy_version),
                         "chunks": len(chunks), "complete": complete, "decisions": len(reward),
                         "return": float(reward.sum()), "final_depth": float(depth[-1]) if len(depth) else float("nan"),
                         "max_depth": float(np.nanmax(depth)) if np.isfinite(depth).any() else float("nan")})
    out["episodes"] = episodes
    policy_topics = [arm_topic(a, POLICY) for a in out["arms"]]
    out["policy_versions"] = [int(d.msg.version) for d in read_messages(bag, policy_topics)]
    return out


def plot_run(bag: str | Path, out: str | Path) -> Path:
    """A PNG of the run: joint positions, applied torques, and the task status (insertion depth,
    contact force) over simulated time, resets marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    traj = joint_trajectory(bag)
    status = task_status(bag)
    t0 = traj.t[0] if len(traj.t) else 0.0
    fig, axes = plt.subplots(4, 1, figsize=(10, 10), sharex=True)
    for i, name in enumerate(traj.names):
        axes[0].plot(traj.t - t0, traj.q[:, i], lw=0.8, label=name)
        axes[1].plot(traj.t - t0, traj.effort[:, i], lw=0.8)
    axes[0].set_ylabel("q [rad]")
    axes[0].legend(fontsize=7, ncol=4)
    axes[1].set_ylabel("torque [Nm]")
    if len(status["t"]):
        axes[2].plot(status["t"] - t0, status["insertion_depth"] * 1e3)
        axes[3].plot(status["t"] - t0, status["contact_force"])
    axes[2].set_ylabel("insertion depth [mm]")
    axes[3].set_ylabel("contact force [N]")
    axes[3].set_xlabel("simulated time [s]")
    for r in traj.resets():
        for ax in axes:
            ax.axvline(traj.t[r] - t0, color="k", lw=0.5, ls="--")
    fig.suptitle(f"{Path(bag).name}: {len(traj.t)} joint states, {len(traj.resets())} resets (dashed)")
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    """``python -m nf_bags.reader BAG [--plot out.png]``: print the run's summary (JSON)."""
    import argparse
    import json

    parser = argparse.ArgumentParser(prog="python -m nf_bags.reader", description=main.__doc__)
    parser.add_argument("bag")
    parser.add_argument("--plot", type=Path, help="write a PNG of joint trajectories and task status")
    args = parser.parse_args(argv)
    from .bagfile import BagError

    try:
        print(json.dumps(summarize(args.bag), indent=1))
        if args.plot:
            print(f"plot: {plot_run(args.bag, args.plot)}")
    except (BagError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
