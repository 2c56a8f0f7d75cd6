"""A tolerant MCAP reader: every message that can still be read from a damaged or torn file.

The ``mcap`` library's readers stop at the first bad record. This one walks the data section record
by record with explicit bounds checks, and when a record cannot be read it notes what was lost and
resynchronises: at the next chunk the summary's chunk index names (when the file has an intact
summary), else at the next offset where a whole chunk parses and decompresses. A chunk whose
compressed data is damaged gives the records decompressed before the damage; a chunk whose CRC does
not match is kept (its records parse; the ``mcap`` reader reads them too) and reported as suspect.
Schemas and channels come from the chunks and from the summary, so a message whose chunk lost its
channel record is still read in a closed file. Nothing here raises for bad bytes: what was skipped
is in ``McapScan.damage``.
"""

from __future__ import annotations

import mmap
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from mcap.records import Channel, Message, Schema

MAGIC = b"\x89MCAP0\r\n"
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, CHUNK_INDEX = 1, 2, 3, 4, 5, 6, 7, 8
ATTACHMENT, ATTACHMENT_INDEX, STATISTICS, METADATA, METADATA_INDEX, SUMMARY_OFFSET, DATA_END = range(9, 16)
_FOOTER_SIZE = 9 + 20  # opcode, length, summary_start, summary_offset_start, summary_crc
_COMPRESSIONS = ("", "zstd", "lz4")
_MAX_UNCOMPRESSED = 1 << 31  # a chunk claiming more is damaged


class _BadRecordError(Exception):
    """A record does not parse (internal)."""


class _Buf:
    """Bounds-checked little-endian reads from ``view[start:end]``."""

    def __init__(self, view: memoryview, start: int, end: int) -> None:
        self.v, self.p, self.end = view, start, end

    def take(self, n: int) -> memoryview:
        if n < 0 or self.p + n > self.end:
            raise _BadRecordError(f"record field runs past its end ({n} bytes at {self.p}, end {self.end})")
        out = self.v[self.p:self.p + n]
        self.p += n
        return out

    def u16(self) -> int:
        return struct.unpack_from("<H", self.take(2))[0]

    def u32(self) -> int:
        return struct.unpack_from("<I", self.take(4))[0]

    def u64(self) -> int:
        return struct.unpack_from("<Q", self.take(8))[0]

    def string(self) -> str:
        try:
            return bytes(self.take(self.u32())).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise _BadRecordError(f"string is not UTF-8: {exc}") from None

    def strmap(self) -> dict[str, str]:
        n = self.u32()
        stop = self.p + n
        if stop > self.end:
            raise _BadRecordError("map runs past its record")
        out = {}
        while self.p < stop:
            k = self.string()
            out[k] = self.string()
        if self.p != stop:
            raise _BadRecordError("map length does not match its entries")
        return out


@dataclass
class Damage:
    """One part of a file that could not be read (or was read with a doubt)."""

    offset: int  # byte offset in the file
    length: int  # bytes affected (0 if unknown)
    what: str  # human-readable reason
    messages_lost: int | None = None  # messages known lost there (from the indexes), None if unknown
    suspect_messages: int = 0  # messages kept although their chunk's CRC does not match

    def __str__(self) -> str:
        lost = "" if self.messages_lost is None else f", {self.messages_lost} messages lost"
        kept = f", {self.suspect_messages} messages kept (CRC mismatch: bytes may be damaged)" \
            if self.suspect_messages else ""
        return f"at byte {self.offset} ({self.length} bytes): {self.what}{lost}{kept}"


@dataclass
class McapScan:
    """What a tolerant pass over one file found."""

    path: Path
    size: int = 0
    magic_ok: bool = False
    has_footer: bool = False  # a footer record and the closing magic at the end
    data_end: bool = False  # the DataEnd record was read (the writer finished the data section)
    summary_ok: bool = False  # the summary section parsed completely
    summary_message_count: int | None = None  # from the summary's Statistics record
    chunks: int = 0  # chunks read (fully or partly)
    damage: list[Damage] = field(default_factory=list)
    torn_bytes: int = 0  # unreadable bytes at the end of a file without footer (a crash)
    readable_bytes: int = 0  # offset after the last record read
    orphans: int = 0  # messages whose channel record is lost (not readable: no topic)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)  # Metadata records by name
    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)

    @property
    def closed(self) -> bool:
        """The writer finished the file (DataEnd or footer present)."""
        return self.has_footer or self.data_end


@dataclass
class _ChunkIndex:
    start: int
    length: int
    index_offsets: dict[int, int]


def _decompress(compression: str, data: bytes | memoryview, size: int) -> tuple[bytes, str]:
    """Decompressed bytes and '' (or as much as decompresses before damage, and why it stopped)."""
    if compression == "":
        return bytes(data), ""
    if compression == "zstd":
        import zstandard

        try:
            return zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=max(size, 1)), ""
        except zstandard.ZstdError as exc:
            whole = str(exc)
        out = []
        obj = zstandard.ZstdDecompressor().decompressobj()
        raw = bytes(data)
        try:
            for i in range(0, len(raw), 4096):
                out.append(obj.decompress(raw[i:i + 4096]))
        except zstandard.ZstdError:
            pass
        return b"".join(out), f"zstd: {whole}"
    if compression == "lz4":
        import lz4.frame

        try:
            return lz4.frame.decompress(bytes(data)), ""
        except RuntimeError as exc:
            return b"", f"lz4: {exc}"
    return b"", f"unknown compression {compression!r}"


class McapScanner:
    """Reads one file tolerantly; iterate ``messages()`` once, then look at ``scan``."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.scan = McapScan(self.path)
        self._index: list[_ChunkIndex] = []

    # ------------------------------------------------------------------ public
    def messages(self) -> Iterator[tuple[Channel, Schema | None, Message]]:
        """Every readable message in file order, with its channel and schema."""
        with open(self.path, "rb") as f:
            self.scan.size = size = f.seek(0, 2)
            if size == 0:
                self.scan.damage.append(Damage(0, 0, "empty file"))
                return
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                view = self._view = memoryview(mm)
                try:
                    yield from self._walk(view, size)
                finally:
                    self._view = None
                    view.release()

    # ------------------------------------------------------------------ walking
    def _walk(self, v: memoryview, size: int) -> Iterator[tuple[Channel, Schema | None, Message]]:
        s = self.scan
        s.magic_ok = size >= 8 and bytes(v[:8]) == MAGIC
        if not s.magic_ok:
            s.damage.append(Damage(0, min(8, size), "no MCAP magic at the start"))
        limit = self._read_summary(v, size)
        pos = 8
        index_starts = sorted(c.start for c in self._index)
        indexed = set(index_starts)
        while pos < limit:
            try:
                if pos in indexed:  # the summary says a chunk starts here: trust it over the opcode
                    pos, items = self._chunk(v, pos, limit)
                    s.readable_bytes = pos
                    yield from items
                    continue
                rec = self._header(v, pos, limit)
                if rec is None:
                    raise _BadRecordError("record runs past the end")
                op, length = rec
                end = pos + 9 + length
                b = _Buf(v, pos + 9, end)
                if op == CHUNK:
                    pos, items = self._chunk(v, pos, limit)
                    s.readable_bytes = pos
                    yield from items
                    continue
                if op == MESSAGE:
                    item = self._resolve(self._message(b, length))
                    if item is not None:
                        yield item
                elif op in (SCHEMA, CHANNEL):
                    self._schema_or_channel(op, b)
                elif op == METADATA:
                    name = b.string()
                    s.metadata[name] = b.strmap()
                elif op == MESSAGE_INDEX:
                    b.u16()
                    n = b.u32()
                    b.take(n)
                    if n % 16:
                        raise _BadRecordError("message index length")
                elif op == HEADER and pos == 8:
                    b.string()
                    b.string()
                elif op == ATTACHMENT:
                    b.u64()
                    b.u64()
                    b.string()
                    b.string()
                    b.take(b.u64())
                    b.u32()
                elif op == DATA_END:
                    b.u32()
                    s.data_end = True
                elif op != FOOTER:
                    raise _BadRecordError(f"opcode {op:#x} where the data section goes on")
                if b.p != end and op != MESSAGE:
                    raise _BadRecordError("record length does not match its fields")
                if op in (DATA_END, FOOTER):
                    s.readable_bytes = end
                    return
                pos = end
                s.readable_bytes = pos
            except _BadRecordError:
                try:  # a chunk whose opcode or length field is damaged still reads from its own fields
                    nxt, items = self._chunk(v, pos, limit, any_opcode=True)
                except _BadRecordError:
                    nxt = self._resync(v, pos, limit, index_starts)
                    if nxt is None:
                        self._tail(pos, limit, size)
                        return
                    self._note_gap(pos, nxt)
                    pos = nxt
                    continue
                s.readable_bytes = pos = nxt
                yield from items

    def _tail(self, pos: int, limit: int, size: int) -> None:
        """Nothing readable from ``pos`` to ``limit``: a torn tail after a crash, or damage."""
        s = self.scan
        if s.has_footer:
            s.damage.append(Damage(pos, limit - pos, "unreadable up to the summary",
                                   messages_lost=self._index_messages_from(pos)))
        else:
            s.torn_bytes = size - pos

    def _note_gap(self, pos: int, nxt: int) -> None:
        self.scan.damage.append(Damage(pos, nxt - pos, "unreadable bytes skipped",
                                       messages_lost=self._index_messages_between(pos, nxt)))

    @staticmethod
    def _header(v: memoryview, pos: int, limit: int) -> tuple[int, int] | None:
        if pos + 9 > limit:
            return None
        op, length = struct.unpack_from("<BQ", v, pos)
        if pos + 9 + length > limit:
            return None
        return op, length

    # ------------------------------------------------------------------ records
    def _schema_or_channel(self, op: int, b: _Buf) -> None:
        if op == SCHEMA:
            sid = b.u16()
            name = b.string()
            encoding = b.string()
            data = bytes(b.take(b.u32()))
            if sid:
                self.scan.schemas.setdefault(sid, Schema(id=sid, name=name, encoding=encoding, data=data))
        else:
            cid = b.u16()
            schema_id = b.u16()
            topic = b.string()
            encoding = b.string()
            metadata = b.strmap()
            self.scan.channels.setdefault(cid, Channel(id=cid, topic=topic, message_encoding=encoding,
                                                       metadata=metadata, schema_id=schema_id))

    @staticmethod
    def _message(b: _Buf, length: int) -> Message:
        if length < 22:
            raise _BadRecordError("message record too short")
        cid, seq, log_time, publish_time = struct.unpack_from("<HIQQ", b.take(22))
        return Message(channel_id=cid, sequence=seq, log_time=log_time, publish_time=publish_time,
                       data=bytes(b.take(length - 22)))

    def _resolve(self, msg: Message) -> tuple[Channel, Schema | None, Message] | None:
        channel = self.scan.channels.get(msg.channel_id)
        if channel is None:
            self.scan.orphans += 1
            return None
        return channel, self.scan.schemas.get(channel.schema_id), msg

    def _chunk_fields(self, v: memoryview, content: int, limit: int) -> tuple[int, str, int, int, int, int]:
        """(end, compression, uncompressed_size, crc, data_start, data_len) of a chunk whose content
        starts at ``content``; the end comes from the inner lengths, not the record's length field."""
        b = _Buf(v, content, limit)
        b.u64()
        b.u64()
        usize = b.u64()
        crc = b.u32()
        n = b.u32()
        if n > 8:
            raise _BadRecordError("implausible compression name")
        try:
            compression = bytes(b.take(n)).decode("ascii")
        except UnicodeDecodeError:
            raise _BadRecordError("compression name is not ASCII") from None
        if compression not in _COMPRESSIONS:
            raise _BadRecordError(f"unknown compression {compression!r}")
        if usize > _MAX_UNCOMPRESSED:
            raise _BadRecordError("implausible uncompressed size")
        dlen = b.u64()
        start = b.p
        b.take(dlen)
        return b.p, compression, usize, crc, start, dlen

    def _chunk(self, v: memoryview, pos: int, limit: int, any_opcode: bool = False
               ) -> tuple[int, list[tuple[Channel, Schema | None, Message]]]:
        """Read the chunk record at ``pos``; returns (offset after it, its readable messages). The
        record's end comes from the chunk's own fields. Raises ``_BadRecordError`` if not even its first record
        can be read (``any_opcode``: also when it reads only in part: the opcode byte is no evidence)."""
        end, compression, usize, crc, start, dlen = self._chunk_fields(v, pos + 9, limit)
        data, error = _decompress(compression, v[start:start + dlen], usize)
        strict = any_opcode and v[pos] != CHUNK
        if not data or (strict and (error or len(data) != usize)):
            raise _BadRecordError(error or "chunk decompresses to nothing")
        records: list[Message] = []
        inner_error = ""
        p, n = 0, len(data)
        unpack = struct.unpack_from
        while p < n:
            if p + 9 > n:
                inner_error = "torn record at the end of the chunk"
                break
            op, length = unpack("<BQ", data, p)
            rec_end = p + 9 + length
            if rec_end > n:
                inner_error = "record runs past the end of the chunk"
                break
            if op == MESSAGE:
                if length < 22:
                    inner_error = "message record too short"
                    break
                cid, seq, log_time, publish_time = unpack("<HIQQ", data, p + 9)
                records.append(Message(channel_id=cid, sequence=seq, log_time=log_time, publish_time=publish_time,
                                       data=data[p + 31:rec_end]))
            elif op in (SCHEMA, CHANNEL):
                try:
                    self._schema_or_channel(op, _Buf(memoryview(data), p + 9, rec_end))
                except _BadRecordError as exc:
                    inner_error = str(exc)
                    break
            p = rec_end
        if strict and (inner_error or not records):
            raise _BadRecordError(inner_error or "no message in the chunk")
        if not records and inner_error and not error:
            raise _BadRecordError(inner_error)
        channels, schemas = self.scan.channels, self.scan.schemas
        items = []
        for m in records:
            channel = channels.get(m.channel_id)
            if channel is None:
                self.scan.orphans += 1
            else:
                items.append((channel, schemas.get(channel.schema_id), m))
        self.scan.chunks += 1
        crc_bad = crc != 0 and not error and not inner_error and zlib.crc32(data) != crc
        if error or inner_error or (len(data) != usize and not error):
            expected = self._index_messages_at(pos)
            lost = None if expected is None else max(0, expected - len(records))
            reason = error or inner_error or f"uncompressed size {len(data)} != {usize} in its header"
            self.scan.damage.append(Damage(pos, end - pos, f"damaged chunk ({reason}); "
                                           f"{len(records)} messages read before the damage", lost))
        elif crc_bad:
            self.scan.damage.append(Damage(pos, end - pos, "chunk CRC mismatch", 0, suspect_messages=len(records)))
        else:
            op, length = struct.unpack_from("<BQ", v, pos)
            if op != CHUNK or length != end - pos - 9:
                self.scan.damage.append(Damage(pos, 9, "chunk opcode or length field damaged (read from the "
                                               "chunk's own fields)", 0))
        return end, items

    # ------------------------------------------------------------------ resync
    def _resync(self, v: memoryview, bad: int, limit: int, index_starts: list[int]) -> int | None:
        """Offset of the next readable record after ``bad`` (a chunk, or the DataEnd record)."""
        for start in index_starts:  # the summary knows where the chunks are
            if start > bad and self._chunk_ok(v, start, limit, any_opcode=True):
                return start
        p = bad + 1
        while p < limit:
            p = self._find(v, p, limit)
            if p is None:
                return None
            if v[p] == DATA_END:
                if self._data_end_ok(v, p, limit):
                    return p
            elif self._chunk_ok(v, p, limit):
                return p
            p += 1
        return None

    @staticmethod
    def _find(v: memoryview, p: int, limit: int) -> int | None:
        """Next offset >= p holding a chunk or DataEnd opcode."""
        raw = v.obj if isinstance(v.obj, (bytes, mmap.mmap)) else bytes(v)
        a = raw.find(b"\x06", p, limit)
        b = raw.find(b"\x0f", p, limit)
        found = [x for x in (a, b) if x >= 0]
        return min(found) if found else None

    def _chunk_ok(self, v: memoryview, p: int, limit: int, any_opcode: bool = False) -> bool:
        if p + 9 > limit or (v[p] != CHUNK and not any_opcode):
            return False
        try:
            _end, compression, usize, _crc, start, dlen = self._chunk_fields(v, p + 9, limit)
        except _BadRecordError:
            return False
        data, error = _decompress(compression, v[start:start + dlen], usize)
        return bool(data) and not error and len(data) == usize

    @staticmethod
    def _data_end_ok(v: memoryview, p: int, limit: int) -> bool:
        if p + 13 > limit:
            return False
        op, length = struct.unpack_from("<BQ", v, p)
        return op == DATA_END and length == 4 and p + 13 == limit

    # ------------------------------------------------------------------ summary
    def _read_summary(self, v: memoryview, size: int) -> int:
        """Parse footer and summary (schemas, channels, chunk indexes, statistics); returns the end
        of the data section to walk (the summary start, or the file size without a footer)."""
        s = self.scan
        if size < 8 + _FOOTER_SIZE + 8 or bytes(v[size - 8:]) != MAGIC:
            return size
        fpos = size - 8 - _FOOTER_SIZE
        op, length = struct.unpack_from("<BQ", v, fpos)
        if op != FOOTER or length != 20:
            s.damage.append(Damage(fpos, _FOOTER_SIZE, "footer damaged"))
            return size
        summary_start, _, summary_crc = struct.unpack_from("<QQI", v, fpos + 9)
        s.has_footer = True
        if summary_start == 0:
            return fpos
        if not 8 <= summary_start <= fpos:
            s.damage.append(Damage(fpos, _FOOTER_SIZE, "footer points outside the file"))
            return fpos
        if summary_crc and zlib.crc32(v[summary_start:fpos + 9 + 16]) != summary_crc:
            s.damage.append(Damage(summary_start, fpos + _FOOTER_SIZE - summary_start,
                                   "summary CRC mismatch (its chunk index is not trusted; the data section is read "
                                   "record by record)"))
            s.summary_ok = False
            return summary_start
        pos = summary_start
        ok = True
        while pos < fpos:
            rec = self._header(v, pos, fpos)
            if rec is None:
                ok = False
                break
            op, length = rec
            b = _Buf(v, pos + 9, pos + 9 + length)
            try:
                if op in (SCHEMA, CHANNEL):
                    self._schema_or_channel(op, b)
                elif op == CHUNK_INDEX:
                    b.u64()
                    b.u64()
                    start = b.u64()
                    clen = b.u64()
                    n = b.u32()
                    offsets = {}
                    stop = b.p + n
                    while b.p < stop:
                        cid = b.u16()
                        offsets[cid] = b.u64()
                    if 8 <= start < summary_start and start + clen <= summary_start:
                        self._index.append(_ChunkIndex(start, clen, offsets))
                elif op == STATISTICS:
                    s.summary_message_count = b.u64()
            except _BadRecordError:
                ok = False
                break
            pos += 9 + length
        s.summary_ok = ok
        if not ok:
            s.damage.append(Damage(pos, fpos - pos, "summary section damaged (the data section is read instead)"))
        return summary_start

    def _index_messages_at(self, chunk_start: int) -> int | None:
        """Messages in the chunk at ``chunk_start`` according to its message index records."""
        entry = next((c for c in self._index if c.start == chunk_start), None)
        if entry is None or self._view is None:
            return None
        total = 0
        for offset in entry.index_offsets.values():
            rec = self._header(self._view, offset, self.scan.size)
            if rec is None or rec[0] != MESSAGE_INDEX:
                return None
            try:
                b = _Buf(self._view, offset + 9, offset + 9 + rec[1])
                b.u16()
                n = b.u32()
            except _BadRecordError:
                return None
            total += n // 16
        return total

    def _index_messages_between(self, a: int, b: int) -> int | None:
        if not self._index:
            return None
        counts = [self._index_messages_at(c.start) for c in self._index if a <= c.start < b]
        return None if any(c is None for c in counts) else sum(counts)  # type: ignore[misc]

    def _index_messages_from(self, a: int) -> int | None:
        return self._index_messages_between(a, 1 << 62)

    _view: memoryview | None = None
