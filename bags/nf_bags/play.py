"""Replay: ``python -m nf_bags.play BAG [--rate R | --fast] [--topics T ...] [--ros-args ...]``.

Publishes a bag's messages back onto their topics, as the recorded CDR bytes (raw publishing: no
decoding, the subscribers get exactly what was recorded), with the recorded timing (receive
times) scaled by ``--rate``, or as fast as possible. Each topic gets the QoS its publishers
offered (reliable/best effort, transient local/volatile). Before the first message it waits up
to ``--wait`` s for every topic to have a subscriber; after the last, for reliable deliveries to
be acknowledged.
"""

from __future__ import annotations

import argparse
import queue
import signal
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import rclpy
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from .bagfile import BagError, RawMessage, iter_raw, load_metadata
from .record import message_class


def recorded_qos(bag: str | Path, depth: int = 1000) -> dict[str, QoSProfile]:
    """Per topic: reliable if every recorded publisher was, transient local if every one was."""
    out = {}
    for entry in load_metadata(bag).get("topics_with_message_count", []):
        meta = entry["topic_metadata"]
        profiles = meta.get("offered_qos_profiles") or []
        if isinstance(profiles, str):  # rosbag2 before version 9 stored a YAML string
            import yaml

            profiles = yaml.safe_load(profiles) or []
        reliable = all(str(p.get("reliability", "reliable")).lower() in ("reliable", "1") for p in profiles)
        latched = bool(profiles) and all(str(p.get("durability", "")).lower() in ("transient_local", "1")
                                         for p in profiles)
        out[meta["name"]] = QoSProfile(
            history=HistoryPolicy.KEEP_LAST, depth=depth,
            reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)
    return out


READ_AHEAD = 1000  # messages decoded ahead of the replay (rosbag2 player's default queue)


def read_ahead(messages: Iterator[RawMessage], stop: threading.Event, depth: int = READ_AHEAD) -> Iterator[RawMessage]:
    """``messages``, read and decompressed by a thread up to ``depth`` ahead: a timed replay then never
    waits at a chunk boundary while its next message is due (as rosbag2's player reads ahead)."""
    items: queue.Queue = queue.Queue(maxsize=depth)
    end = object()
    done = threading.Event()  # the consumer left: the reader stops too

    def put(item: object) -> bool:
        while not (done.is_set() or stop.is_set()):
            try:
                items.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def reader() -> None:
        try:
            for raw in messages:
                if not put(raw):
                    return
            put(end)
        except BaseException as exc:  # handed to the consumer, raised there
            put(exc)

    thread = threading.Thread(target=reader, name="bag-read-ahead", daemon=True)
    thread.start()  # now, not at the first next(): it reads while the caller waits for subscribers

    def consume() -> Iterator[RawMessage]:
        try:
            while not stop.is_set():
                try:
                    item = items.get(timeout=0.1)
                except queue.Empty:
                    continue
                if item is end:
                    return
                if isinstance(item, BaseException):
                    raise item
                yield item
        finally:
            done.set()
            thread.join(timeout=1.0)

    return consume()


def play(node: Any, bag: str | Path, rate: float | None, topics: list[str] | None, wait: float,
         stop: threading.Event) -> int:
    """Publish the bag's messages with ``node``; ``rate`` None = as fast as possible. Returns the count."""
    wanted = {node.resolve_topic_name(t) for t in topics} if topics else None
    qos = recorded_qos(bag)
    types: dict[str, str] = {}
    for raw in iter_raw(bag, wanted):  # one pass to learn the types (cheap next to the replay)
        types.setdefault(raw.topic, raw.type)
    classes, bad = {}, []
    for topic, msg_type in types.items():
        try:
            classes[topic] = message_class(msg_type)
        except (ValueError, LookupError) as exc:
            bad.append(f"{topic}: {exc}")
    if bad:
        raise ValueError("cannot replay these topics (leave them out with --topics): " + "; ".join(bad))
    publishers: dict[str, Any] = {}
    for topic, cls in classes.items():
        profile = qos.get(topic, QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        publishers[topic] = node.create_publisher(cls, topic, profile)
    messages = read_ahead(iter_raw(bag, wanted), stop)  # reads while the subscribers match
    deadline = time.monotonic() + wait
    while time.monotonic() < deadline and not stop.is_set():
        if all(p.get_subscription_count() > 0 for p in publishers.values()):
            time.sleep(0.1)  # let the subscribers' side finish matching too
            break
        time.sleep(0.02)
    count = 0
    t_wall = time.monotonic()
    t_bag: int | None = None
    for raw in messages:
        if stop.is_set():
            break
        if rate is not None:
            t_bag = raw.log_time if t_bag is None else t_bag
            due = t_wall + (raw.log_time - t_bag) * 1e-9 / rate
            delay = due - time.monotonic()
            if delay > 0:
                stop.wait(delay)
        publishers[raw.topic].publish(raw.data)
        count += 1
    for p in publishers.values():
        p.wait_for_all_acked(Duration(seconds=2.0))
    return count


def main(argv: list[str] | None = None) -> int:
    """Console entry: replay until the bag ends or SIGINT/SIGTERM."""
    argv = list(sys.argv if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m nf_bags.play", description=__doc__.splitlines()[0],
                                     epilog="ROS arguments follow --ros-args (e.g. -r __ns:=/arm1).")
    parser.add_argument("bag", type=Path)
    timing = parser.add_mutually_exclusive_group()
    timing.add_argument("--rate", type=float, default=1.0, help="playback speed factor (1: recorded timing)")
    timing.add_argument("--fast", action="store_true", help="as fast as possible")
    parser.add_argument("--topics", nargs="+", help="only these topics")
    parser.add_argument("--wait", type=float, default=2.0, help="s to wait for subscribers before starting")
    args = parser.parse_args(remove_ros_args(argv)[1:])
    if not args.fast and not args.rate > 0.0:
        parser.error(f"--rate must be > 0, got {args.rate}")
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda *_: stop.set()) for sig in (signal.SIGINT, signal.SIGTERM)}
    ros_args = argv[:1] + (argv[argv.index("--ros-args"):] if "--ros-args" in argv else [])
    rclpy.init(args=ros_args, signal_handler_options=SignalHandlerOptions.NO)
    node = rclpy.create_node("nf_bag_player")
    try:
        t0 = time.monotonic()
        try:
            count = play(node, args.bag, None if args.fast else args.rate, args.topics, args.wait, stop)
        except (BagError, ValueError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        node.get_logger().info(f"published {count} messages in {time.monotonic() - t0:.2f} s")
        return 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":
    raise SystemExit(main())
