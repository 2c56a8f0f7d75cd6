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
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args

from nf_controller_node.ros_runtime import run_node

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


class RecorderNode(Node):
    """Raw subscriptions feeding a ``BagWriter``; see the module docstring."""

    def __init__(self, options: RecorderOptions) -> None:
        super().__init__("nf_bag_recorder")
        self.options = options
        self.writer = BagWriter(options.output, options.writer)
        self._wanted = {self.resolve_topic_name(t) for t in options.topics}
        self._subscribed: dict[str, object] = {}
        self._skipped: set[str] = set()
        self._t0 = time.monotonic()
        self._discover()
        self.create_timer(options.discovery_period, self._discover)
        self.create_timer(min(0.1, options.writer.chunk_seconds / 4), self.writer.tick)
        what = ", ".join(sorted(self._wanted)) if self._wanted else "all topics"
        self.get_logger().info(f"recording {what} into {options.output}")

    def _discover(self) -> None:
        for topic, types in self.get_topic_names_and_types():
            if topic in self._subscribed or topic in self._skipped:
                continue
            if self._wanted and topic not in self._wanted:
                continue
            if not self._wanted and _hidden(topic) and not self.options.include_hidden:
                continue
            if len(types) != 1:
                self.get_logger().warn(f"not recording {topic}: it has several types {types}")
                self._skipped.add(topic)
                continue
            self._subscribe(topic, types[0])

    def _subscribe(self, topic: str, msg_type: str) -> None:
        publishers = [p for p in self.get_publishers_info_by_topic(topic) if p.node_name != self.get_name()]
        if not publishers:
            return  # only subscribers so far: wait for a publisher to learn its QoS
        try:
            cls = message_class(msg_type)
            self.writer.add_topic(topic, msg_type, qos=[qos_dict(p.qos_profile) for p in publishers],
                                  type_hash=str(publishers[0].topic_type_hash))
        except (LookupError, ImportError, AttributeError, ValueError) as exc:
            self.get_logger().error(f"not recording {topic} ({msg_type}): {exc}")
            self._skipped.add(topic)
            return
        reliable = all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers)
        latched = all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers)
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=self.options.depth,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
        write = self.writer.write
        now = time.time_ns

        def on_message(data: bytes) -> None:  # rclpy 7.1's EventsExecutor gives no MessageInfo
            write(topic, data, now())

        self._subscribed[topic] = self.create_subscription(cls, topic, on_message, qos, raw=True)
        self.get_logger().info(f"recording {topic} ({msg_type}, {'reliable' if reliable else 'best effort'}"
                               f"{', transient local' if latched else ''})")

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
