"""Reading a bag's raw records, also after a crash or damage: ``metadata.yaml`` and every readable
message of its ``.mcap`` files (in file order, which is arrival order), without ROS.

The files are read with ``nf_bags.mcapscan``, a tolerant reader: a file whose recorder was killed
(no summary, a torn last record) reads up to its last complete chunk, and a damaged chunk is
skipped (found again through the summary's chunk index, else by resynchronising on the next whole
chunk) with the rest of the file read on. ``scan`` says what was cut off or skipped and compares
with the counts of the last metadata update. ``repair`` writes a repaired copy, never touching the
original. Bad input (a missing path, a sqlite3 bag, an invalid metadata.yaml) raises ``BagError``
with a message for the user.
"""

from __future__ import annotations

import copy
import os
import shutil
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from mcap.records import Channel, Schema

from .mcapscan import MAGIC, Damage, McapScan, McapScanner
from .writer import (
    CHUNK_SECONDS_KEY,
    METADATA,
    METADATA_SECONDS_KEY,
    PENDING_SINCE_KEY,
    STATE_KEY,
    UPDATED_KEY,
)

LOST_KEY = "nf_bags.lost_messages"  # custom_data after ``repair``: messages the crash cost (known)
DROPPED_KEY = "nf_bags.repair_dropped"  # custom_data after ``repair``: what the repair could not keep
REPAIRED_SUFFIX = ".repaired"

_Loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
_REQUIRED = ("version", "storage_identifier", "relative_file_paths", "message_count", "topics_with_message_count")


class BagError(ValueError):
    """A bag that cannot be read at all (missing, unsupported, invalid metadata); the message says why."""


@dataclass(frozen=True)
class RawMessage:
    """One recorded message: CDR bytes and where/when it was recorded."""

    topic: str
    type: str  # pkg/msg/Type
    log_time: int  # ns since epoch, when the recorder received it
    publish_time: int  # ns since epoch, when it was published (source timestamp)
    sequence: int
    data: bytes
    schema: Schema | None
    channel: Channel


@dataclass
class FileScan:
    """What one ``.mcap`` file holds."""

    path: Path
    size: int = 0
    complete: bool = False  # the writer finished it (data end / footer present)
    chunks: int = 0
    counts: Counter = field(default_factory=Counter)  # readable messages per topic
    first_time: int | None = None  # log time range of the readable messages (ns)
    last_time: int | None = None
    readable_bytes: int = 0  # offset after the last record read
    torn: int = 0  # unreadable bytes at the end of a file the writer did not finish (a crash)
    damage: list[Damage] = field(default_factory=list)  # skipped or doubtful parts
    orphans: int = 0  # messages whose channel record is lost
    summary_messages: int | None = None  # message count of the file's summary (closed files)
    embedded_metadata: dict[str, dict[str, str]] = field(default_factory=dict)  # MCAP Metadata records

    @property
    def torn_bytes(self) -> int:
        """Bytes after the last readable record of an unfinished file (a chunk being written at a crash)."""
        return self.torn

    @property
    def damaged(self) -> bool:
        """Something in the file could not be read, or was read with a doubt (CRC)."""
        return bool(self.damage) or self.orphans > 0

    @property
    def messages(self) -> int:
        """Readable messages."""
        return sum(self.counts.values())

    def _fill(self, s: McapScan) -> None:
        self.size, self.complete, self.chunks = s.size, s.closed, s.chunks
        self.readable_bytes, self.torn, self.damage = s.readable_bytes, s.torn_bytes, list(s.damage)
        self.orphans, self.summary_messages, self.embedded_metadata = s.orphans, s.summary_message_count, s.metadata


# ---------------------------------------------------------------------- opening a bag
def _check_metadata(meta: Any, path: Path) -> dict[str, Any]:
    if not isinstance(meta, dict) or not isinstance(meta.get("rosbag2_bagfile_information"), dict):
        raise BagError(f"{path} is not rosbag2 metadata (no rosbag2_bagfile_information mapping)")
    info = meta["rosbag2_bagfile_information"]
    storage = info.get("storage_identifier", "mcap")
    absent = [k for k in _REQUIRED if k not in info]
    if absent and storage == "mcap":
        raise BagError(f"{path} is incomplete (truncated?): no {', '.join(absent)}")
    if storage != "mcap":
        raise BagError(f"{path.parent} is a {storage!r} bag; nf_bags reads MCAP bags only "
                       f"(convert it with `ros2 bag convert`, storage mcap)")
    files = info.get("relative_file_paths")
    if not isinstance(info.get("message_count"), int):
        raise BagError(f"{path} is invalid: message_count is not a number")
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        raise BagError(f"{path} is incomplete or invalid: relative_file_paths is not a list of file names")
    topics = info.get("topics_with_message_count", [])
    try:
        for t in topics or []:
            str(t["topic_metadata"]["name"])
            str(t["topic_metadata"]["type"])
            int(t["message_count"])
    except (KeyError, TypeError, ValueError) as exc:
        raise BagError(f"{path} is incomplete or invalid: topics_with_message_count ({exc!r})") from None
    if not isinstance(info.get("custom_data") or {}, dict):
        raise BagError(f"{path} is invalid: custom_data is not a mapping")
    return info


def load_metadata(bag: str | Path) -> dict[str, Any]:
    """The ``rosbag2_bagfile_information`` of ``bag/metadata.yaml`` ({} if there is none); ``BagError``
    for a file that is not valid YAML or not rosbag2 metadata (truncated, other storage)."""
    path = Path(bag) / METADATA
    if not path.is_file():
        return {}
    try:
        meta = yaml.load(path.read_text(), Loader=_Loader)
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise BagError(f"{path} is not valid YAML (truncated or damaged?): {first}") from None
    return _check_metadata(meta, path)


def _mcap_magic(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(8) == MAGIC
    except OSError:
        return False


def mcap_files(bag: str | Path) -> list[Path]:
    """The bag's ``.mcap`` files in recording order (metadata.yaml's list, else by split index).
    ``BagError`` if ``bag`` is missing, unsupported, or its metadata names a file that is not there."""
    bag = Path(bag)
    if not bag.exists():
        raise BagError(f"no such bag: {bag} does not exist")
    if bag.is_file():
        if bag.name == METADATA:
            return mcap_files(bag.parent)
        if bag.suffix == ".db3":
            raise BagError(f"{bag} is a sqlite3 bag file; nf_bags reads MCAP bags only "
                           f"(convert it with `ros2 bag convert`, storage mcap)")
        if not _mcap_magic(bag) and bag.suffix != ".mcap":
            raise BagError(f"{bag} is not an MCAP file (no MCAP magic) and not a bag directory")
        return [bag]
    meta = load_metadata(bag)
    names = [Path(p).name for p in meta.get("relative_file_paths", [])]
    missing = [n for n in names if not (bag / n).is_file()]
    if missing:
        raise BagError(f"{bag / METADATA} lists {', '.join(missing)}, which "
                       f"{'is' if len(missing) == 1 else 'are'} missing from {bag}")
    found = {p.name for p in bag.glob("*.mcap")}
    if names:  # a single file's repaired copy next to it is not part of the bag
        found = {n for n in found if n in names or not n.endswith(REPAIRED_SUFFIX + ".mcap")}
    if not meta and not found:
        if any(bag.glob("*.db3")):
            raise BagError(f"{bag} holds sqlite3 bag files (.db3); nf_bags reads MCAP bags only")
        raise BagError(f"{bag} is not a bag: no {METADATA} and no .mcap file")
    ordered = [bag / n for n in names]

    def index(p: Path) -> tuple[int, str]:
        tail = p.stem.rsplit("_", 1)[-1]
        return (int(tail) if tail.isdigit() else 1 << 30, p.name)

    ordered += sorted((bag / n for n in found if n not in names), key=index)
    return ordered


# ---------------------------------------------------------------------- reading
def iter_file(path: str | Path, topics: set[str] | None = None, scan: FileScan | None = None) -> Iterator[RawMessage]:
    """Every readable message of one ``.mcap`` file (optionally only ``topics``), damage skipped;
    ``scan`` (when given) is filled with what was read and skipped once the iteration ends."""
    scan = scan if scan is not None else FileScan(Path(path))
    scanner = McapScanner(path)
    try:
        for channel, schema, msg in scanner.messages():
            topic = channel.topic
            scan.counts[topic] += 1
            t = msg.log_time
            scan.first_time = t if scan.first_time is None else min(scan.first_time, t)
            scan.last_time = t if scan.last_time is None else max(scan.last_time, t)
            if topics is None or topic in topics:
                yield RawMessage(topic, schema.name if schema is not None else "", t, msg.publish_time,
                                 msg.sequence, msg.data, schema, channel)
    finally:
        scan._fill(scanner.scan)


def iter_raw(bag: str | Path, topics: Any = None) -> Iterator[RawMessage]:
    """Every readable message of a bag (a directory or one ``.mcap`` file), file after file."""
    wanted = set(topics) if topics else None
    for path in mcap_files(bag):
        yield from iter_file(path, wanted)


# ---------------------------------------------------------------------- health
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
    def custom(self) -> dict[str, Any]:
        """metadata.yaml's custom_data."""
        return self.metadata.get("custom_data") or {}

    @property
    def finished(self) -> bool:
        """The recorder (or ``repair``) finished every file and the metadata does not say recording."""
        return self.custom.get(STATE_KEY, "closed") != "recording" and all(f.complete for f in self.files)

    @property
    def damaged(self) -> bool:
        """Some file has a part that could not be read (or a CRC mismatch)."""
        return any(f.damaged for f in self.files)

    @property
    def closed(self) -> bool:
        """Closed cleanly and intact: every file finished, nothing skipped."""
        return self.finished and not self.damaged

    @property
    def state(self) -> str:
        """``closed`` | ``repaired`` | ``damaged`` (finished, but parts unreadable) | ``unclosed`` (recorder died)."""
        if not self.finished:
            return "unclosed"
        if self.damaged:
            return "damaged"
        return "repaired" if self.custom.get(STATE_KEY) == "repaired" else "closed"

    @property
    def metadata_counts(self) -> dict[str, int]:
        """Messages per topic as counted by the last metadata.yaml update."""
        return {t["topic_metadata"]["name"]: int(t["message_count"])
                for t in self.metadata.get("topics_with_message_count", [])}

    @property
    def lost(self) -> dict[str, int]:
        """Per topic: messages the metadata counted that no file holds (known lost: a lower bound)."""
        have = self.counts
        return {k: v - have.get(k, 0) for k, v in self.metadata_counts.items() if v > have.get(k, 0)}

    def last_readable(self) -> int | None:
        """Log time (ns) of the last readable message."""
        return max((f.last_time for f in self.files if f.last_time is not None), default=None)

    def loss_window(self) -> tuple[float, float] | None:
        """After a crash: (s from the last readable message to the last metadata update, the
        recorder's chunk period); None for a finished bag. See ``loss_bound``."""
        if self.finished:
            return None
        custom = self.custom
        last = self.last_readable()
        updated = int(custom.get(UPDATED_KEY, 0) or 0) or None
        chunk = float(custom.get(CHUNK_SECONDS_KEY, 0.0) or 0.0)
        if last is None or updated is None:
            return (0.0, chunk)
        return (max(0.0, (updated - last) * 1e-9), chunk)

    def loss_bound(self) -> dict[str, Any] | None:
        """After a crash, what the files say about the lost messages (None for a finished bag).

        The recorder cuts its chunks by the receive time of the messages themselves: a chunk never
        spans ``chunk_seconds`` or more, and a crash loses the open chunk (and one being written).
        Every lost message the recorder had taken was received after ``last_readable_ns`` and within
        ``chunk_seconds`` of the lost chunk's first message. When the last metadata update counted
        messages that are not in the files, that first message arrived before the update (or is the
        ``pending since`` time it names), so the loss ends at most ``chunk_seconds`` later: a bound
        that holds whatever the timers did (``guaranteed``). Without counted losses the lost chunk
        began after the update; its end is bounded only if the recorder's timers ran on time (it
        would have written the next update within ``metadata_seconds``).
        """
        if self.finished:
            return None
        custom = self.custom
        last = self.last_readable()
        updated = int(custom.get(UPDATED_KEY, 0) or 0) or None
        pending = int(custom.get(PENDING_SINCE_KEY, 0) or 0) or None
        chunk = float(custom.get(CHUNK_SECONDS_KEY, 0.0) or 0.0)
        period = float(custom.get(METADATA_SECONDS_KEY, 0.0) or 0.0)
        counted = sum(self.lost.values())
        out: dict[str, Any] = {"last_readable_ns": last, "metadata_updated_ns": updated,
                               "pending_since_ns": pending, "chunk_seconds": chunk,
                               "metadata_seconds": period, "lost_at_least": counted}
        if updated is None or not chunk:
            out.update(lost_until_ns=None, guaranteed=False)
        elif counted:
            start = pending if pending is not None and pending <= updated else updated
            out.update(lost_until_ns=start + int(chunk * 1e9), guaranteed=True)
        else:
            out.update(lost_until_ns=updated + int((period + chunk) * 1e9), guaranteed=False)
        if out["lost_until_ns"] is not None and last is not None:
            out["lost_span_at_most_s"] = max(0.0, (out["lost_until_ns"] - last) * 1e-9)
        elif last is None and counted:  # nothing readable: the lost messages are one chunk
            out["lost_span_at_most_s"] = chunk
        else:
            out["lost_span_at_most_s"] = None
        return out

    def problems(self) -> list[str]:
        """One line per damaged part, torn tail, orphan message or doubtful chunk."""
        lines = []
        for f in self.files:
            for d in f.damage:
                kind = "kept, doubtful" if d.suspect_messages else "skipped"
                lines.append(f"{f.path.name}: {kind}: {d}")
            if f.orphans:
                lines.append(f"{f.path.name}: {f.orphans} messages whose channel record is lost (no topic): skipped")
            if f.torn:
                lines.append(f"{f.path.name}: {f.torn} torn bytes at the end (the chunk being written when the "
                             f"recorder died)")
        return lines

    def report(self) -> str:
        """A human-readable summary, like ``ros2 bag info`` plus the crash and damage report."""
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
            if f.complete and not f.damaged:
                state = "complete"
            elif f.complete:
                state = "complete but DAMAGED"
            else:
                state = f"NO SUMMARY ({f.torn} torn bytes at the end)"
            total = f" of {f.summary_messages} in its summary" if f.summary_messages is not None \
                and f.summary_messages != f.messages else ""
            lines.append(f"  {f.path.name}: {f.messages} messages{total}, {f.chunks} chunks, {state}")
        types = {t["topic_metadata"]["name"]: t["topic_metadata"]["type"]
                 for t in meta.get("topics_with_message_count", [])}
        lines.append("topics:")
        for name in sorted(set(types) | set(counts)):
            mc = self.metadata_counts.get(name)
            extra = f" (metadata {mc})" if mc is not None and mc != counts.get(name, 0) else ""
            lines.append(f"  {name}  {types.get(name, '?')}  {counts.get(name, 0)}{extra}")
        problems = self.problems()
        if problems:
            lines.append("damage:")
            lines += [f"  {p}" for p in problems]
        custom = self.custom
        state = self.state
        if state == "repaired":
            lines.append(f"state:      repaired copy; the original lost {custom.get(LOST_KEY, '?')} messages counted "
                         f"by its metadata{'; ' + str(custom[DROPPED_KEY]) if custom.get(DROPPED_KEY) else ''}")
        elif state == "closed":
            lines.append("state:      closed cleanly")
        elif state == "damaged":
            lines.append("state:      DAMAGED: the recorder closed the bag, but parts of it are damaged (listed above; "
                         "every message that can be read is read). `--repair` writes a repaired copy")
        else:
            b = self.loss_bound() or {}
            lost = b.get("lost_at_least", 0)
            chunk = b.get("chunk_seconds", 0.0)
            if b.get("lost_span_at_most_s") is None:
                bound = "no bound known (metadata without update time)"
            elif b.get("guaranteed"):
                bound = f"received at most {b['lost_span_at_most_s']:.3f} s after the last readable message"
            else:
                bound = (f"received at most {b['lost_span_at_most_s']:.3f} s after the last readable message "
                         f"if the recorder's timers ran on time (no update after the last one)")
            lines.append(
                f"state:      NOT CLOSED (recorder died): every complete chunk is readable; lost: at least {lost} "
                f"messages (counted by the last metadata update, not in the files); the lost messages lie in one "
                f"chunk (< {chunk:g} s of receive time), {bound}; messages still queued in the recorder when it "
                f"died are lost too and counted nowhere")
        return "\n".join(lines)


def scan(bag: str | Path) -> BagScan:
    """Read every file of ``bag`` to the end (skipping damage) and compare with the metadata."""
    bag = Path(bag)
    if bag.is_file() and bag.name == METADATA:
        bag = bag.parent
    files = []
    for path in mcap_files(bag):
        s = FileScan(path)
        for _ in iter_file(path, set(), s):
            pass
        files.append(s)
    return BagScan(bag, files, load_metadata(bag) if bag.is_dir() else {})


# ---------------------------------------------------------------------- repair
@dataclass
class RepairResult:
    """What ``repair`` did: the scan of the original, where the copy is, what it holds and dropped."""

    before: BagScan
    output: Path | None  # None: nothing to repair, nothing written
    messages: int  # messages in the copy (= readable messages of the original)
    dropped: list[str]  # the original's damage: what the copy does not have, and what it kept with a doubt

    def report(self) -> str:
        """Human-readable lines."""
        if self.output is None:
            return "repair:     nothing to repair (closed cleanly, nothing damaged); nothing written"
        lines = [f"repair:     wrote {self.output}: {self.messages} messages, every message readable in the "
                 f"original (which is left as it was)"]
        dropped = [d for d in self.dropped if "kept, doubtful" not in d]
        kept = [d for d in self.dropped if "kept, doubtful" in d]
        lines += [f"  dropped: {d}" for d in dropped] or ["  dropped: nothing"]
        lines += [f"  kept although its chunk's CRC did not match (written with a new CRC; the original's "
                  f"bytes may have been damaged): {d}" for d in kept]
        return "\n".join(lines)


def repaired_path(bag: str | Path) -> Path:
    """Default output of ``repair``: ``<bag>.repaired`` (a directory) or ``<name>.repaired.mcap``."""
    bag = Path(bag)
    if bag.is_file():
        return bag.with_name(bag.stem + REPAIRED_SUFFIX + bag.suffix)
    return bag.with_name(bag.name + REPAIRED_SUFFIX)


def _rewrite(src: Path, dst: Path, embedded: dict[str, str] | None) -> int:
    """Write every readable message of ``src`` into a new, whole file ``dst``; returns the count."""
    from mcap.writer import CompressionType
    from mcap.writer import Writer as McapWriter

    n = 0
    with open(dst, "xb") as out:
        writer = McapWriter(out, compression=CompressionType.ZSTD)
        writer.start(profile="ros2", library="nf_bags repair")
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        for raw in iter_file(src):
            ch = raw.channel
            if ch.id not in channel_ids:
                sid = 0
                if raw.schema is not None:
                    if raw.schema.id not in schema_ids:
                        schema_ids[raw.schema.id] = writer.register_schema(raw.schema.name, raw.schema.encoding,
                                                                           raw.schema.data)
                    sid = schema_ids[raw.schema.id]
                channel_ids[ch.id] = writer.register_channel(ch.topic, ch.message_encoding, sid, ch.metadata)
            writer.add_message(channel_ids[ch.id], raw.log_time, raw.data, raw.publish_time, raw.sequence)
            n += 1
        if embedded is not None:
            writer.add_metadata("rosbag2", embedded)
        writer.finish()
    return n


def repair(bag: str | Path, output: str | Path | None = None) -> RepairResult:
    """Write a repaired copy of ``bag`` (like ``ros2 bag reindex``, but never in place): every
    readable message of every file, each file whole again (summary, indexes), and a metadata.yaml
    with the counts the copy holds; ``nf_bags.state: repaired`` and the original's known loss stay on
    record in ``custom_data``. The original is not modified. Nothing is written for a bag that is
    closed cleanly and undamaged. ``output`` defaults to ``repaired_path(bag)`` and must not exist.
    The copy is read back: it must hold every message the original's reading gives, else it is
    removed and ``BagError`` raised."""
    bag = Path(bag)
    if bag.is_file() and bag.name == METADATA:
        bag = bag.parent
    before = scan(bag)
    if before.closed:
        return RepairResult(before, None, sum(before.counts.values()), [])
    out = Path(output) if output is not None else repaired_path(bag)
    if out.exists():
        raise BagError(f"{out} exists: remove it or name another output (--output)")
    dropped = before.problems()
    single = bag.is_file()
    try:
        if single:
            total = _rewrite(bag, out, None)
        else:
            out.mkdir(parents=True)
            total = 0
            meta = _repaired_metadata(before)
            for f in before.files:
                dst = out / f.path.name
                if f.complete and not f.damaged:
                    shutil.copy2(f.path, dst)
                    total += f.messages
                else:
                    embedded = {"serialized_metadata": yaml.safe_dump(meta, sort_keys=False), "ros_distro": "jazzy"}
                    total += _rewrite(f.path, dst, embedded)
            text = yaml.safe_dump({"rosbag2_bagfile_information": meta}, sort_keys=False)
            (out / METADATA).write_text(text)
        after = scan(out)
        if after.counts != before.counts or after.state not in ("closed", "repaired"):
            raise BagError(f"the repaired copy {out} does not read back whole ({dict(after.counts)} vs "
                           f"{dict(before.counts)}); removed")
    except BaseException:
        if out.is_dir():
            shutil.rmtree(out, ignore_errors=True)
        elif out.exists():
            out.unlink()
        raise
    return RepairResult(before, out, total, dropped)


def _repaired_metadata(before: BagScan) -> dict[str, Any]:
    """metadata.yaml of the repaired copy: the original's (or one built from the files), with the
    counts and times the copy holds."""
    meta = copy.deepcopy(before.metadata)
    counts = before.counts
    if not meta:
        topics: dict[str, dict[str, Any]] = {}
        for f in before.files:
            for raw in iter_file(f.path):
                if raw.topic not in topics:
                    qos = raw.channel.metadata.get("offered_qos_profiles", "")
                    topics[raw.topic] = {"name": raw.topic, "type": raw.type, "serialization_format": "cdr",
                                         "offered_qos_profiles": yaml.safe_load(qos) if qos else [],
                                         "type_description_hash": raw.channel.metadata.get("topic_type_hash", "")}
        meta = {"version": 9, "storage_identifier": "mcap",
                "topics_with_message_count": [{"topic_metadata": t, "message_count": 0} for t in topics.values()],
                "compression_format": "", "compression_mode": "", "ros_distro": "jazzy"}
    meta["relative_file_paths"] = [f.path.name for f in before.files]
    for entry in meta.get("topics_with_message_count", []):
        entry["message_count"] = counts.get(entry["topic_metadata"]["name"], 0)
    meta["message_count"] = sum(counts.values())
    firsts = [f.first_time for f in before.files if f.first_time is not None]
    lasts = [f.last_time for f in before.files if f.last_time is not None]
    if firsts:
        meta["starting_time"] = {"nanoseconds_since_epoch": min(firsts)}
        meta["duration"] = {"nanoseconds": max(lasts) - min(firsts)}
    meta["files"] = [{"path": f.path.name,
                      "starting_time": {"nanoseconds_since_epoch": f.first_time or 0},
                      "duration": {"nanoseconds": (f.last_time or 0) - (f.first_time or 0)},
                      "message_count": f.messages} for f in before.files]
    custom = dict(meta.get("custom_data") or {})
    custom[STATE_KEY] = "repaired"
    custom[LOST_KEY] = str(sum(before.lost.values()))
    problems = before.problems()
    if problems:
        custom[DROPPED_KEY] = "; ".join(problems)
    meta["custom_data"] = custom
    return meta


def file_size(path: str | Path) -> int:
    """Size in bytes (0 if missing)."""
    try:
        return os.path.getsize(path)
    except OSError:
        return 0
