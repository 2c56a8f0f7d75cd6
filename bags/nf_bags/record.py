"""Recorder node: ``python -m nf_bags.record [-o DIR] [--topics T ...] [...] [--ros-args ...]``.

Subscribes to the chosen topics (or to every topic it discovers, hidden ones excepted) with raw
subscriptions, so the bag holds exactly the CDR bytes that were published, and hands them to
``nf_bags.writer.BagWriter``. Like rosbag2's recorder, it matches the publishers' QoS (reliable if
all of them are, transient local if all of them are, so a latched policy is caught) and keeps
looking for new topics. The receive time (system clock, taken in the callback) is the log and the
publish time (rclpy 7.1's EventsExecutor cannot hand over the message info). Stops cleanly on
SIGINT/SIGTERM and closes the bag; after a ``kill -9`` every chunk written so far stays readable
(``python -m nf_bags.info DIR``).
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args

from nf_core.ros_runtime import run_node

from .writer import BagWriter, WriterConfig, qos_dict

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"


@dataclass
class RecorderOptions:
    """What to record and where; built from the command line in ``main``."""

    output: Path
    topics: list[str] = field(default_factory=list)  # empty: every topic discovered
    include_hidden: bool = False  # with no topic list: also topics whose name has a part starting with "_"
    depth: int = 1000  # queue depth of each subscription (reader side: a slow recorder buffers, not drops)
    discovery_period: float = 0.5  # s between looks for new topics
    writer: WriterConfig = field(default_factory=WriterConfig)


def message_class(msg_type: str) -> type:
    """The generated Python class of ``pkg/msg/Type`` (``pkg/Type`` is read as ``pkg/msg/Type``);
    ``ValueError`` for a malformed name, ``LookupError`` for a type that is not installed."""
    parts = str(msg_type).split("/")
    if len(parts) == 2:
        parts = [parts[0], "msg", parts[1]]
    if len(parts) != 3 or not all(p.isidentifier() for p in parts) or parts[1] != "msg":
        raise ValueError(f"not a message type name: {msg_type!r} (expected pkg/msg/Type)")
    package, kind, name = parts
    try:
        module = importlib.import_module(f"{package}.{kind}")
    except ImportError:
        raise LookupError(f"message type {msg_type} is not installed (no Python package {package!r}: source the "
                          f"workspace that builds it)") from None
    cls = getattr(module, name, None)
    if not isinstance(cls, type):
        raise LookupError(f"message type {msg_type} is not installed ({package} has no message {name!r})")
    return cls


def _hidden(topic: str) -> bool:
    return any(part.startswith("_") for part in topic.split("/"))


DEDUP_SECONDS = 3.0  # after a (re)subscription: how long history samples are checked against what was recorded
RECENT = 64  # hashes of the last messages per topic kept for that check
RETRY_SECONDS = 30.0  # a topic that cannot be recorded (several types, type not importable) is retried this long


@dataclass
class _Recorded:
    """One recorded topic: its subscriptions and what they were made for."""

    cls: type
    msg_type: str
    publishers: frozenset = frozenset()  # endpoint GIDs of the publishers the QoS was chosen for
    main: Any = None  # the subscription that records
    reliable: bool = True
    latched: bool = False
    main_dedup_until: float = 0.0  # monotonic: messages of ``main`` equal to a recent one are history
    catchup: Any = None  # transient-local subscription for latched history when publishers are mixed
    catchup_until: float = 0.0  # monotonic: after this, ``catchup`` messages are live duplicates: dropped
    recent: deque = field(default_factory=lambda: deque(maxlen=RECENT))
    replayed: Counter = field(default_factory=Counter)  # after a resubscription: recorded, not yet seen again


class RecorderNode(Node):
    """Raw subscriptions feeding a ``BagWriter``; see the module docstring.

    QoS: a topic is subscribed once a publisher of it is seen: reliable if every publisher is,
    transient local if every publisher is. Every discovery round looks at the publishers again
    (late joiners): a new best-effort or volatile publisher makes the subscription follow (else it
    would be incompatible and record nothing of it); publishers that are all transient local again
    make it transient local. When transient-local and volatile publishers are mixed, a second,
    transient-local subscription takes the latched history of the transient-local ones (its
    messages already recorded, or arriving later as live duplicates, are dropped by content).
    """

    def __init__(self, options: RecorderOptions) -> None:
        super().__init__("nf_bag_recorder")
        self.options = options
        self.writer = BagWriter(options.output, options.writer)
        self._wanted = {self.resolve_topic_name(t) for t in options.topics}
        self._subscribed: dict[str, _Recorded] = {}
        self._skipped: set[str] = set()  # given up on (after RETRY_SECONDS of failures)
        self._failures: dict[str, float] = {}  # topic -> monotonic time of its first failure
        self._t0 = time.monotonic()
        self._discover()
        self.create_timer(options.discovery_period, self._discover)
        self.create_timer(min(0.1, options.writer.chunk_seconds / 4), self.writer.tick)
        what = ", ".join(sorted(self._wanted)) if self._wanted else "all topics"
        self.get_logger().info(f"recording {what} into {options.output}")

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subscribed:
                self._recheck(topic)
                continue
            if topic in self._skipped:
                continue
            if self._wanted and topic not in self._wanted:
                continue
            if not self._wanted and _hidden(topic) and not self.options.include_hidden:
                continue
            if len(types) != 1:
                self._failed(topic, f"it has several types {types}")
                continue
            self._subscribe(topic, types[0])

    def _failed(self, topic: str, reason: str) -> None:
        """A topic that cannot be recorded now: retried every round for ``RETRY_SECONDS`` (graph
        information and installed types can lag behind a starting node), then given up, loudly."""
        now = time.monotonic()
        first = self._failures.setdefault(topic, now)
        if first == now:
            self.get_logger().warn(f"not recording {topic} yet: {reason}; retrying for {RETRY_SECONDS:g} s")
        elif now - first > RETRY_SECONDS:
            self.get_logger().error(f"not recording {topic}: {reason}")
            self._skipped.add(topic)

    def _offers(self, topic: str) -> list:
        return [p for p in self.get_publishers_info_by_topic(topic) if p.node_name != self.get_name()]

    def _sub_qos(self, reliable: bool, latched: bool) -> QoSProfile:
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=self.options.depth,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)

    def _subscribe(self, topic: str, msg_type: str) -> None:
        publishers = self._offers(topic)
        if not publishers:
            return  # only subscribers so far: wait for a publisher to learn its QoS
        try:
            cls = message_class(msg_type)
            self.writer.add_topic(topic, msg_type, qos=[qos_dict(p.qos_profile) for p in publishers],
                                  type_hash=str(publishers[0].topic_type_hash))
        except (LookupError, ImportError, AttributeError, ValueError) as exc:
            self._failed(topic, f"({msg_type}) {exc}")
            return
        if self._failures.pop(topic, None) is not None:
            self.get_logger().info(f"{topic}: recordable now")
        rec = _Recorded(cls, msg_type)
        self._subscribed[topic] = rec
        self._recheck(topic, publishers)
        self.get_logger().info(f"recording {topic} ({msg_type}, {'reliable' if rec.reliable else 'best effort'}"
                               f"{', transient local' if rec.latched else ''}"
                               f"{', latched history of the transient-local ones' if rec.catchup else ''})")

    def _recheck(self, topic: str, publishers: list | None = None) -> None:
        """Follow the publishers' QoS (see the class docstring); cheap when they did not change."""
        rec = self._subscribed[topic]
        publishers = self._offers(topic) if publishers is None else publishers
        gids = frozenset(bytes(p.endpoint_gid) for p in publishers)
        if not publishers or gids == rec.publishers:
            return
        new = [p for p in publishers if bytes(p.endpoint_gid) not in rec.publishers]
        rec.publishers = gids
        reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
        latched = [p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers]
        all_latched, any_latched = all(latched), any(latched)
        now = time.monotonic()
        first = rec.main is None
        # reliability only ever goes down (a reliable reader cannot match a best-effort writer)
        want_reliable = rec.reliable and reliable if not first else reliable
        if first or want_reliable != rec.reliable or all_latched != rec.latched:
            old = rec.main
            rec.reliable, rec.latched = want_reliable, all_latched
            rec.main = self.create_subscription(rec.cls, topic, self._on_message(topic, rec, False),
                                                self._sub_qos(rec.reliable, rec.latched), raw=True)
            # only a transient-local reader is sent history: a volatile one gets live messages alone, and
            # a live message equal to a recorded one (a lockstep resend) must not be taken for history
            rec.main_dedup_until = 0.0 if first or not rec.latched else now + DEDUP_SECONDS
            rec.replayed = Counter(rec.recent)  # each recorded message can come again once, as history
            if old is not None:
                self.destroy_subscription(old)
                self.get_logger().info(f"{topic}: publishers changed, now recording it "
                                       f"{'reliable' if rec.reliable else 'best effort'}"
                                       f"{', transient local' if rec.latched else ''}")
        if any_latched and not all_latched and any(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                                                   for p in new):
            if rec.catchup is not None:
                self.destroy_subscription(rec.catchup)
            # history reaches reliable readers only: reliable if the transient-local publishers all are
            keep = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers
                       if p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL)
            rec.catchup = self.create_subscription(rec.cls, topic, self._on_message(topic, rec, True),
                                                   self._sub_qos(keep, True), raw=True)
            rec.catchup_until = now + DEDUP_SECONDS
            if not first:
                self.get_logger().info(f"{topic}: a transient-local publisher joined volatile ones: taking its "
                                       f"latched history")
        elif all_latched and rec.catchup is not None:
            self.destroy_subscription(rec.catchup)
            rec.catchup = None

    def _on_message(self, topic: str, rec: _Recorded, catchup: bool) -> Callable[[bytes], None]:
        write = self.writer.write
        now = time.time_ns
        clock = time.monotonic
        recent = rec.recent

        def on_message(data: bytes) -> None:  # rclpy 7.1's EventsExecutor gives no MessageInfo
            if catchup or rec.main_dedup_until:
                until = rec.catchup_until if catchup else rec.main_dedup_until
                if clock() > until:
                    if catchup:
                        return  # a live message the main subscription records too
                    rec.main_dedup_until = 0.0
                elif catchup and hash(data) in recent:
                    return  # history already recorded
                elif not catchup and rec.replayed[hash(data)] > 0:
                    rec.replayed[hash(data)] -= 1
                    return  # history the previous subscription recorded
            recent.append(hash(data))
            write(topic, data, now())

        return on_message

    def destroy_node(self) -> None:
        """Close the bag (last chunk, summary, final metadata.yaml), then the node."""
        if not self.writer.closed:
            self.writer.close()
            counts = ", ".join(f"{t.name}: {t.count}" for t in self.writer.topics.values())
            self.get_logger().info(f"closed {self.options.output}: {self.writer.message_count} messages in "
                                   f"{time.monotonic() - self._t0:.1f} s ({counts})")
        super().destroy_node()

def build_parser() -> argparse.ArgumentParser:
    """The recorder's command line (ROS arguments after --ros-args pass through)."""
    p = argparse.ArgumentParser(prog="python -m nf_bags.record", description=__doc__.splitlines()[0],
                                epilog="ROS arguments follow --ros-args (e.g. -r __ns:=/arm1).")
    p.add_argument("-o", "--output", type=Path, default=None,
                   help=f"bag directory (must not exist or be empty); default {RECORDINGS}/<date_time>")
    p.add_argument("--topics", nargs="+", default=[], help="topics to record (default: all discovered)")
    p.add_argument("--include-hidden", action="store_true", help="with no --topics: also hidden topics")
    p.add_argument("--depth", type=int, default=1000, help="subscription queue depth")
    c = WriterConfig()
    p.add_argument("--chunk-bytes", type=int, default=c.chunk_bytes, help="uncompressed bytes per chunk")
    p.add_argument("--chunk-seconds", type=float, default=c.chunk_seconds,
                   help="s of wall time after which an open chunk is written (bounds the loss on a crash)")
    p.add_argument("--split-bytes", type=int, default=0, help="start a new .mcap file after N bytes (0: never)")
    p.add_argument("--split-seconds", type=float, default=0.0, help="start a new .mcap file after N s (0: never)")
    p.add_argument("--metadata-seconds", type=float, default=c.metadata_seconds,
                   help="s between metadata.yaml updates")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default=c.compression)
    return p


def options_from_args(args: argparse.Namespace) -> RecorderOptions:
    """``RecorderOptions`` from parsed arguments (``ValueError`` for bad values)."""
    if args.depth < 1:
        raise ValueError(f"--depth must be >= 1, got {args.depth}")
    config = WriterConfig(chunk_bytes=args.chunk_bytes, chunk_seconds=args.chunk_seconds,
                          split_bytes=args.split_bytes, split_seconds=args.split_seconds,
                          metadata_seconds=args.metadata_seconds, compression=args.compression)
    config.check()
    output = args.output or RECORDINGS / time.strftime("%Y%m%d_%H%M%S")
    if output.exists() and (not output.is_dir() or any(output.iterdir())):
        raise ValueError(f"output {output} exists and is not an empty directory")
    return RecorderOptions(output=output, topics=list(args.topics), include_hidden=args.include_hidden,
                           depth=args.depth, writer=config)


def ros_part(argv: Sequence[str]) -> list[str]:
    """The program name and the ``--ros-args ...`` part of ``argv``."""
    argv = list(argv)
    return argv[:1] + (argv[argv.index("--ros-args"):] if "--ros-args" in argv else [])


def main(argv: list[str] | None = None) -> int:
    """Console entry: parse, then run the node until SIGINT/SIGTERM."""
    argv = list(sys.argv if argv is None else argv)
    parser = build_parser()
    args = parser.parse_args(remove_ros_args(argv)[1:])
    try:
        options = options_from_args(args)
    except ValueError as exc:
        parser.error(str(exc))
    return run_node(lambda: RecorderNode(options), "nf_bag_recorder", parser.description or "", ros_part(argv))


if __name__ == "__main__":
    raise SystemExit(main())
