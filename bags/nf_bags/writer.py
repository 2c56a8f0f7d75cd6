"""ROS-free core of the recorder: writes a rosbag2 bag (a directory with ``metadata.yaml`` and
``<name>_<i>.mcap`` files) from serialized (CDR) messages, with the ``mcap`` library.

- Chunks: zstd-compressed, closed after ``chunk_bytes`` of messages or ``chunk_seconds``: a
  message received ``chunk_seconds`` or more after the open chunk's first message closes that
  chunk before it is added (so a chunk never spans ``chunk_seconds`` of receive time, whatever the
  timers do), and ``tick`` closes a due chunk when no message arrives. Each closed chunk is written
  and flushed to the OS at once, so a killed recorder (``kill -9``) leaves every closed chunk
  readable; only the open one (less than ``chunk_seconds`` of messages) is lost, plus what the
  recorder had not yet taken from its queues.
- Splits: a new ``.mcap`` file after ``split_bytes`` or ``split_seconds`` (0: never).
- ``metadata.yaml`` (rosbag2 version 9) is written at start, when a topic is added, every
  ``metadata_seconds`` and at close. It counts every message received so far, so after a crash
  the difference to what the files hold is what was lost (see ``nf_bags.info``). Its
  ``custom_data`` says ``nf_bags.state: recording`` until the bag is closed.
- Schemas are ``ros2msg`` definitions (``nf_bags.schemas``), channels carry the offered QoS
  profiles and the type hash in their metadata, as rosbag2's MCAP plugin does.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter

from .schemas import MESSAGE_ENCODING, SCHEMA_ENCODING, message_definition

METADATA = "metadata.yaml"
ROSBAG2_VERSION = 9
STATE_KEY = "nf_bags.state"  # custom_data: recording | closed (| split: a file closed for a split | repaired)
UPDATED_KEY = "nf_bags.updated_ns"  # custom_data: wall time (ns since epoch) of the last metadata update
CHUNK_SECONDS_KEY = "nf_bags.chunk_seconds"
METADATA_SECONDS_KEY = "nf_bags.metadata_seconds"
PENDING_SINCE_KEY = "nf_bags.pending_since_ns"  # custom_data: log time of the open chunk's first message
INFINITE_DURATION = {"sec": 9223372036, "nsec": 854775807}  # RMW_DURATION_INFINITE, as rosbag2 Jazzy writes it
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
_Dumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)


@dataclass(frozen=True)
class WriterConfig:
    """How the bag is cut into chunks and files; ``check`` names the first bad value."""

    chunk_bytes: int = 512 * 1024  # uncompressed bytes of messages per chunk
    chunk_seconds: float = 1.0  # s of wall time before an open chunk is written out
    split_bytes: int = 0  # start a new .mcap file after this many bytes (0: never)
    split_seconds: float = 0.0  # start a new .mcap file after this many s of recorded time (0: never)
    metadata_seconds: float = 0.5  # s of wall time between metadata.yaml updates
    compression: str = "zstd"  # zstd | lz4 | none (per chunk)

    def check(self) -> None:
        """Raise ``ValueError`` with the reason if a value is out of range."""
        if self.chunk_bytes <= 0:
            raise ValueError(f"chunk_bytes must be > 0, got {self.chunk_bytes}")
        if not self.chunk_seconds > 0.0:
            raise ValueError(f"chunk_seconds must be > 0, got {self.chunk_seconds}")
        if self.split_bytes < 0 or not self.split_seconds >= 0.0:
            raise ValueError(f"split_bytes and split_seconds must be >= 0, got {self.split_bytes}, "
                             f"{self.split_seconds}")
        if not self.metadata_seconds > 0.0:
            raise ValueError(f"metadata_seconds must be > 0, got {self.metadata_seconds}")
        if self.compression not in _COMPRESSION:
            raise ValueError(f"compression must be one of {sorted(_COMPRESSION)}, got {self.compression!r}")


@dataclass
class Topic:
    """One recorded topic: what metadata.yaml lists for it."""

    name: str
    type: str  # pkg/msg/Type
    definition: str
    qos: list[dict[str, Any]] = field(default_factory=list)  # rosbag2 v9 offered_qos_profiles
    type_hash: str = ""  # RIHS01_... (empty if unknown)
    count: int = 0


@dataclass
class _File:
    path: Path
    start: int | None = None  # log time (ns) of the first message
    end: int = 0
    count: int = 0


def qos_dict(qos: Any) -> dict[str, Any]:
    """A ``rclpy.qos.QoSProfile`` (or anything with its fields) as a rosbag2 v9 QoS entry."""

    def name(value: Any) -> str:
        return str(getattr(value, "name", value)).lower()

    def duration(value: Any) -> dict[str, int]:
        ns = int(getattr(value, "nanoseconds", 0))
        if ns >= 2**63 - 1 or ns < 0:
            return dict(INFINITE_DURATION)
        return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}

    return {
        "history": name(qos.history), "depth": int(qos.depth), "reliability": name(qos.reliability),
        "durability": name(qos.durability), "deadline": duration(qos.deadline), "lifespan": duration(qos.lifespan),
        "liveliness": name(qos.liveliness), "liveliness_lease_duration": duration(qos.liveliness_lease_duration),
        "avoid_ros_namespace_conventions": bool(qos.avoid_ros_namespace_conventions),
    }


class BagWriter:
    """Writes one bag directory; see the module docstring. Not thread-safe: call from one thread."""

    def __init__(self, path: str | Path, config: WriterConfig | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config or WriterConfig()
        self.config.check()
        self._chunk_ns = int(self.config.chunk_seconds * 1e9)
        self.path = Path(path)
        if self.path.exists() and any(self.path.iterdir()):
            raise FileExistsError(f"bag directory {self.path} exists and is not empty")
        self.path.mkdir(parents=True, exist_ok=True)
        self._clock = clock
        self.topics: dict[str, Topic] = {}
        self.files: list[_File] = []
        self._schema_ids: dict[str, int] = {}
        self._channel_ids: dict[str, int] = {}
        self._mcap: McapWriter | None = None
        self._stream: Any = None
        self._pending_bytes = 0  # message bytes in the open chunk
        self._pending_since: int | None = None  # log time (ns) of the open chunk's first message
        self._chunk_opened = clock()  # clock() at the open chunk's first message (or last flush)
        self._metadata_written = clock()
        self.chunks = 0  # chunks written to disk
        self.closed = False
        self._open_file()
        self.write_metadata()

    # ------------------------------------------------------------------ files
    def _open_file(self) -> None:
        name = f"{self.path.name}_{len(self.files)}.mcap"
        self._stream = open(self.path / name, "wb")
        mcap = McapWriter(self._stream, chunk_size=1 << 40, compression=_COMPRESSION[self.config.compression])
        mcap.start(profile="ros2", library=f"nf_bags (mcap-python) {mcap_library()}")
        mcap.flush()
        self._mcap = mcap
        self.files.append(_File(self.path / name))
        self._schema_ids.clear()
        self._channel_ids.clear()
        for topic in self.topics.values():
            self._register(topic)

    def _close_file(self, final: bool = False) -> None:
        assert self._mcap is not None
        info = self._metadata(state="closed" if final else "split")["rosbag2_bagfile_information"]
        self._mcap.add_metadata("rosbag2", {"serialized_metadata": yaml.dump(info, Dumper=_Dumper, sort_keys=False),
                                            "ros_distro": "jazzy"})
        self._mcap.finish()
        self._stream.close()
        self._mcap = None
        self.chunks += 1 if self._pending_bytes else 0
        self._pending_bytes = 0
        self._pending_since = None

    def _register(self, topic: Topic) -> None:
        assert self._mcap is not None
        if topic.type not in self._schema_ids:
            self._schema_ids[topic.type] = self._mcap.register_schema(
                topic.type, SCHEMA_ENCODING, topic.definition.encode())
        metadata = {"offered_qos_profiles": yaml.dump(topic.qos, Dumper=_Dumper, sort_keys=False)}
        if topic.type_hash:
            metadata["topic_type_hash"] = topic.type_hash
        self._channel_ids[topic.name] = self._mcap.register_channel(
            topic.name, MESSAGE_ENCODING, self._schema_ids[topic.type], metadata)

    # ------------------------------------------------------------------ writing
    def add_topic(self, name: str, msg_type: str, definition: str | None = None,
                  qos: Sequence[dict[str, Any]] = (), type_hash: str = "") -> Topic:
        """Register a topic (``msg_type`` as ``pkg/msg/Type``); the definition is looked up if not given."""
        if name in self.topics:
            raise ValueError(f"topic {name} is already recorded")
        topic = Topic(name, msg_type, definition or message_definition(msg_type), list(qos), type_hash)
        self.topics[name] = topic
        self._register(topic)
        self.write_metadata()
        return topic

    def write(self, topic: str, data: bytes, log_time: int, publish_time: int | None = None,
              sequence: int = 0) -> None:
        """Append one serialized message received at ``log_time`` (ns since epoch)."""
        if self.closed:
            raise RuntimeError("bag is closed")
        t = self.topics[topic]
        current = self.files[-1]
        if current.count and self._split_due(current, log_time):
            self._close_file()
            self._open_file()
            current = self.files[-1]
        elif self._pending_since is not None and log_time - self._pending_since >= self._chunk_ns:
            self.flush()  # the open chunk would span chunk_seconds: write it first
        if self._pending_since is None:
            self._pending_since = log_time
            self._chunk_opened = self._clock()
        assert self._mcap is not None
        self._mcap.add_message(self._channel_ids[topic], log_time, data,
                               log_time if publish_time is None else publish_time, sequence & 0xFFFFFFFF)
        t.count += 1
        current.count += 1
        current.start = log_time if current.start is None else min(current.start, log_time)
        current.end = max(current.end, log_time)
        self._pending_bytes += len(data) + 31  # + the message record's header
        if self._pending_bytes >= self.config.chunk_bytes:
            self.flush()

    def _split_due(self, current: _File, log_time: int) -> bool:
        c = self.config
        if c.split_bytes and self._stream.tell() + self._pending_bytes >= c.split_bytes:
            return True
        return bool(c.split_seconds and current.start is not None
                    and log_time - current.start >= c.split_seconds * 1e9)

    def flush(self) -> None:
        """Write the open chunk (if it holds messages) and hand it to the OS."""
        assert self._mcap is not None
        if self._pending_bytes:
            self._mcap.flush()
            self.chunks += 1
            self._pending_bytes = 0
        self._pending_since = None
        self._chunk_opened = self._clock()

    def tick(self) -> None:
        """Call periodically: writes a chunk that is ``chunk_seconds`` old and a due metadata update."""
        if self.closed:
            return
        now = self._clock()
        if now - self._chunk_opened >= self.config.chunk_seconds:
            self.flush()
        if now - self._metadata_written >= self.config.metadata_seconds:
            self.write_metadata()

    def close(self) -> None:
        """Write the last chunk, the summary and the final metadata.yaml."""
        if self.closed:
            return
        self._close_file(final=True)
        self.closed = True
        self.write_metadata()

    # ------------------------------------------------------------------ metadata
    @property
    def message_count(self) -> int:
        """Messages written (or waiting in the open chunk)."""
        return sum(t.count for t in self.topics.values())

    def _metadata(self, state: str | None = None) -> dict[str, Any]:
        starts = [f.start for f in self.files if f.start is not None]
        start = min(starts) if starts else 0
        end = max((f.end for f in self.files), default=0)
        files = [{"path": f.path.name, "starting_time": {"nanoseconds_since_epoch": f.start or 0},
                  "duration": {"nanoseconds": max(0, f.end - (f.start or f.end))}, "message_count": f.count}
                 for f in self.files]
        topics = [{"topic_metadata": {"name": t.name, "type": t.type, "serialization_format": MESSAGE_ENCODING,
                                      "offered_qos_profiles": t.qos, "type_description_hash": t.type_hash},
                   "message_count": t.count} for t in self.topics.values()]
        custom = {STATE_KEY: state or ("closed" if self.closed else "recording"), UPDATED_KEY: str(time.time_ns()),
                  CHUNK_SECONDS_KEY: str(self.config.chunk_seconds),
                  METADATA_SECONDS_KEY: str(self.config.metadata_seconds)}
        if self._pending_since is not None and not self.closed:
            custom[PENDING_SINCE_KEY] = str(self._pending_since)
        return {"rosbag2_bagfile_information": {
            "version": ROSBAG2_VERSION, "storage_identifier": "mcap",
            "relative_file_paths": [f.path.name for f in self.files],
            "duration": {"nanoseconds": max(0, end - start)},
            "starting_time": {"nanoseconds_since_epoch": start},
            "message_count": self.message_count, "topics_with_message_count": topics,
            "compression_format": "", "compression_mode": "", "files": files,
            "custom_data": custom, "ros_distro": "jazzy",
        }}

    def write_metadata(self) -> None:
        """Replace metadata.yaml atomically with the current counts."""
        text = yaml.dump(self._metadata(), Dumper=_Dumper, sort_keys=False)
        tmp = self.path / (METADATA + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, self.path / METADATA)
        self._metadata_written = self._clock()


def mcap_library() -> str:
    """Version of the mcap library, for the file header."""
    from mcap.writer import LIBRARY_IDENTIFIER

    return LIBRARY_IDENTIFIER
