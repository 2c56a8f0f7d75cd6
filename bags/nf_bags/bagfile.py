"""Reading a bag's raw records, also after a crash: ``metadata.yaml`` and every readable message
of its ``.mcap`` files (in file order, which is arrival order), without ROS.

The files are read record by record with the ``mcap`` library's stream reader, so a file whose
recorder was killed (no summary, maybe a torn last record) reads up to its last complete chunk;
``scan`` says how much was cut off and compares with the counts of the last metadata update.
"""

from __future__ import annotations

import copy
import os
import struct
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Footer, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk

from .writer import CHUNK_SECONDS_KEY, METADATA, METADATA_SECONDS_KEY, STATE_KEY, UPDATED_KEY

LOST_KEY = "nf_bags.lost_messages"  # custom_data after ``repair``: messages the crash cost

_Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


@dataclass(frozen=True)
class RawMessage:
    """One recorded message: CDR bytes and where/when it was recorded."""

    topic: str
    type: str  # pkg/msg/Type
    log_time: int  # ns since epoch, when the recorder received it
    publish_time: int  # ns since epoch, when it was published (source timestamp)
    sequence: int
    data: bytes
    schema: Schema
    channel: Channel


@dataclass
class FileScan:
    """What one ``.mcap`` file holds."""

    path: Path
    size: int = 0
    complete: bool = False  # ended with a footer (closed cleanly)
    chunks: int = 0
    counts: Counter = field(default_factory=Counter)  # readable messages per topic
    first_time: int | None = None  # log time range of the readable messages (ns)
    last_time: int | None = None
    readable_bytes: int = 0  # offset after the last complete record
    error: str = ""  # why reading stopped early

    @property
    def torn_bytes(self) -> int:
        """Bytes after the last complete record (a chunk being written when the recorder died)."""
        return self.size - self.readable_bytes


def load_metadata(bag: str | Path) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` of ``bag/metadata.yaml`` ({} if there is none)."""
    path = Path(bag) / METADATA
    if not path.exists():
        return {}
    return (yaml.load(path.read_text(), Loader=_Loader) or {}).get("rosbag2_bagfile_information", {})


def mcap_files(bag: str | Path) -> list[Path]:
    """The bag's ``.mcap`` files in recording order (metadata.yaml's list, else by split index)."""
    bag = Path(bag)
    if bag.is_file():
        return [bag]
    meta = load_metadata(bag)
    names = [Path(p).name for p in meta.get("relative_file_paths", [])]
    found = {p.name for p in bag.glob("*.mcap")}
    ordered = [bag / n for n in names if n in found]

    def index(p: Path) -> tuple[int, str]:
        tail = p.stem.rsplit("_", 1)[-1]
        return (int(tail) if tail.isdigit() else 1 << 30, p.name)

    ordered += sorted((bag / n for n in found if n not in names), key=index)
    return ordered


def _records(path: Path, scan: FileScan) -> Iterator[Any]:
    """Top-level and in-chunk records of one file; fills ``scan`` and stops quietly at a torn end."""
    scan.size = path.stat().st_size
    with open(path, "rb") as f:
        reader = StreamReader(f, skip_magic=False, emit_chunks=True)
        try:
            for record in reader.records:
                scan.readable_bytes = f.tell()
                if isinstance(record, Chunk):
                    inner = breakup_chunk(record, validate_crc=True)
                    scan.chunks += 1
                    yield from inner
                elif isinstance(record, Footer):
                    scan.complete = True
                    yield record
                else:
                    yield record
        except (McapError, struct.error, ValueError, OSError) as exc:  # a torn tail after a crash
            scan.error = f"{type(exc).__name__}: {exc}"


def iter_file(path: str | Path, topics: set[str] | None = None, scan: FileScan | None = None) -> Iterator[RawMessage]:
    """Every readable message of one ``.mcap`` file (optionally only ``topics``)."""
    scan = scan if scan is not None else FileScan(Path(path))
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    for record in _records(Path(path), scan):
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Message):
            channel = channels[record.channel_id]
            scan.counts[channel.topic] += 1
            if scan.first_time is None:
                scan.first_time = record.log_time
            scan.first_time = min(scan.first_time, record.log_time)
            scan.last_time = max(scan.last_time or 0, record.log_time)
            if topics is None or channel.topic in topics:
                schema = schemas[channel.schema_id]
                yield RawMessage(channel.topic, schema.name, record.log_time, record.publish_time,
                                 record.sequence, record.data, schema, channel)


def iter_raw(bag: str | Path, topics: Any = None) -> Iterator[RawMessage]:
    """Every readable message of a bag (a directory or one ``.mcap`` file), file after file."""
    wanted = set(topics) if topics else None
    for path in mcap_files(bag):
        yield from iter_file(path, wanted)


@dataclass
class BagScan:
    """A bag's health: what its files hold against what its metadata counted."""

    path: Path
    files: list[FileScan]
    metadata: dict[str, Any]

    @property
    def counts(self) -> Counter:
        """Readable messages per topic."""
        total: Counter = Counter()
        for f in self.files:
            total.update(f.counts)
        return total

    @property
    def closed(self) -> bool:
        """The recorder closed the bag, or ``repair`` did (metadata says so and every file has its footer)."""
        custom = self.metadata.get("custom_data") or {}
        return custom.get(STATE_KEY, "closed") in ("closed", "repaired") and all(f.complete for f in self.files)

    @property
    def metadata_counts(self) -> dict[str, int]:
        """Messages per topic as counted by the last metadata.yaml update."""
        return {t["topic_metadata"]["name"]: int(t["message_count"])
                for t in self.metadata.get("topics_with_message_count", [])}

    @property
    def lost(self) -> dict[str, int]:
        """Per topic: messages the metadata counted that no file holds (known lost)."""
        have = self.counts
        return {k: v - have.get(k, 0) for k, v in self.metadata_counts.items() if v > have.get(k, 0)}

    def loss_window(self) -> tuple[float, float] | None:
        """(s of recording known lost, s more that may be) after a crash; None for a closed bag.

        Known: from the last readable message to the last metadata update. Possibly more: one
        metadata period after that update (the recorder died before the next one)."""
        if self.closed:
            return None
        custom = self.metadata.get("custom_data") or {}
        last = max((f.last_time for f in self.files if f.last_time is not None), default=None)
        updated = int(custom.get(UPDATED_KEY, 0)) or None
        period = float(custom.get(METADATA_SECONDS_KEY, 0.0))
        if last is None or updated is None:
            return (0.0, period)
        return (max(0.0, (updated - last) * 1e-9), period)

    def report(self) -> str:
        """A human-readable summary, like ``ros2 bag info`` plus the crash report."""
        meta = self.metadata
        counts = self.counts
        lines = [f"bag:        {self.path}"]
        first = [f.first_time for f in self.files if f.first_time is not None]
        last = [f.last_time for f in self.files if f.last_time is not None]
        if first:
            lines.append(f"duration:   {(max(last) - min(first)) * 1e-9:.3f} s (readable messages)")
        lines.append(f"messages:   {sum(counts.values())} readable; metadata counted {meta.get('message_count', '?')}")
        lines.append(f"files:      {len(self.files)}, chunks {sum(f.chunks for f in self.files)}, "
                     f"{sum(f.size for f in self.files) / 1e6:.2f} MB")
        for f in self.files:
            state = "complete" if f.complete else f"NO SUMMARY ({f.torn_bytes} torn bytes at the end)"
            lines.append(f"  {f.path.name}: {sum(f.counts.values())} messages, {f.chunks} chunks, {state}")
        types = {t["topic_metadata"]["name"]: t["topic_metadata"]["type"]
                 for t in meta.get("topics_with_message_count", [])}
        lines.append("topics:")
        for name in sorted(set(types) | set(counts)):
            mc = self.metadata_counts.get(name)
            extra = f" (metadata {mc})" if mc is not None and mc != counts.get(name, 0) else ""
            lines.append(f"  {name}  {types.get(name, '?')}  {counts.get(name, 0)}{extra}")
        window = self.loss_window()
        custom = meta.get("custom_data") or {}
        if window is None and custom.get(STATE_KEY) == "repaired":
            lines.append(f"state:      repaired after a recorder crash; {custom.get(LOST_KEY, '?')} messages were lost")
        elif window is None:
            lines.append("state:      closed cleanly")
        else:
            known, more = window
            lost = sum(self.lost.values())
            custom = meta.get("custom_data") or {}
            lines.append(
                f"state:      NOT CLOSED (recorder died): every complete chunk is readable; lost: {lost} messages "
                f"counted by the last metadata update ({known:.3f} s after the last readable message), plus "
                f"whatever arrived in the <= {more:g} s before the next update "
                f"(chunks every {custom.get(CHUNK_SECONDS_KEY, '?')} s)")
        return "\n".join(lines)


def scan(bag: str | Path) -> BagScan:
    """Read every file of ``bag`` to the end (or its torn tail) and compare with the metadata."""
    bag = Path(bag)
    files = []
    for path in mcap_files(bag):
        s = FileScan(path)
        for _ in iter_file(path, set(), s):
            pass
        files.append(s)
    return BagScan(bag, files, load_metadata(bag) if bag.is_dir() else {})


def repair(bag: str | Path) -> BagScan:
    """Make a crashed bag whole (like ``ros2 bag reindex``): rewrite every file without a summary
    from its readable records (the torn tail is dropped; nothing readable is lost) and rewrite
    metadata.yaml with the counts the files now hold. The loss stays on record in ``custom_data``
    (``nf_bags.lost_messages``). Returns the scan from before the repair."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    bag = Path(bag)
    before = scan(bag)
    for f in before.files:
        if f.complete:
            continue
        tmp = f.path.with_suffix(".mcap.repairing")
        with open(tmp, "wb") as out:
            writer = McapWriter(out, compression=CompressionType.ZSTD)
            writer.start(profile="ros2", library="nf_bags repair")
            schema_ids: dict[int, int] = {}
            channel_ids: dict[int, int] = {}
            for record in _records(f.path, FileScan(f.path)):
                if isinstance(record, Schema) and record.id not in schema_ids:
                    schema_ids[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel) and record.id not in channel_ids:
                    channel_ids[record.id] = writer.register_channel(
                        record.topic, record.message_encoding, schema_ids.get(record.schema_id, 0), record.metadata)
                elif isinstance(record, Message):
                    writer.add_message(channel_ids[record.channel_id], record.log_time, record.data,
                                       record.publish_time, record.sequence)
            writer.finish()
        os.replace(tmp, f.path)
    after = scan(bag)
    meta = copy.deepcopy(before.metadata)
    counts = after.counts
    for entry in meta.get("topics_with_message_count", []):
        entry["message_count"] = counts.get(entry["topic_metadata"]["name"], 0)
    meta["message_count"] = sum(counts.values())
    for entry, f in zip(meta.get("files", []), after.files, strict=False):
        entry["message_count"] = sum(f.counts.values())
        if f.first_time is not None:
            entry["starting_time"] = {"nanoseconds_since_epoch": f.first_time}
            entry["duration"] = {"nanoseconds": (f.last_time or f.first_time) - f.first_time}
    custom = dict(meta.get("custom_data") or {})
    if custom.get(STATE_KEY) != "closed":
        custom[STATE_KEY] = "repaired"
        custom[LOST_KEY] = str(sum(before.lost.values()))
    meta["custom_data"] = custom
    text = yaml.dump({"rosbag2_bagfile_information": meta}, sort_keys=False)
    tmp = bag / (METADATA + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, bag / METADATA)
    return before


def file_size(path: str | Path) -> int:
    """Size in bytes (0 if missing)."""
    try:
        return os.path.getsize(path)
    except OSError:
        return 0
