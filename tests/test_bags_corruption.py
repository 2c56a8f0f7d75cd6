"""Corruption of the sample bag (no ROS graph): bytes flipped at a few hundred offsets chosen over
every record of ``bags/sample/sample_0.mcap`` (opcodes, lengths, chunk fields, compressed data,
indexes, summary, footer, magic) plus random ones, and truncations. For every variant no tool of
ours (the reader, ``info``, ``info --repair``) may read fewer messages than the best independent
reading (the ``mcap`` package's seeking and non-seeking readers), none may raise, ``info`` may call
the bag closed only when every message is there, and a repair never touches the original and
writes a copy that holds every message we read (checked with the ``mcap`` reader too).
``NF_BAGS_FUZZ_VARIANTS`` (default 60, for the suite's time; 200 were run by hand) bounds the number of variants."""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import random
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from mcap.reader import NonSeekingReader, SeekingReader
from mcap.stream_reader import StreamReader
from nf_bags import bagfile, info

from ros_testing import REPO

SAMPLE = REPO / "bags" / "sample"
FILE = SAMPLE / "sample_0.mcap"
VARIANTS = int(os.environ.get("NF_BAGS_FUZZ_VARIANTS", "60"))
# messages in the intact sample, as its recorder counted them (metadata.yaml's message_count)
SAMPLE_MESSAGES = int(yaml.safe_load((SAMPLE / "metadata.yaml").read_text())
                      ["rosbag2_bagfile_information"]["message_count"])


def independent_count(path: Path, seeking_only: bool = False) -> int:
    """Messages the ``mcap`` package reads from ``path`` before its first error, best of its readers."""
    best = 0
    makers = [lambda f: SeekingReader(f).iter_messages(log_time_order=False),
              lambda f: SeekingReader(f).iter_messages(log_time_order=True),
              lambda f: NonSeekingReader(f).iter_messages()]
    for make in makers[:1] if seeking_only else makers:
        n = 0
        try:
            with open(path, "rb") as f:
                for _ in make(f):
                    n += 1
        except Exception:  # an independent reader failing is what we compare against
            pass
        best = max(best, n)
    return best


def record_offsets(data: bytes) -> list[tuple[int, int, int]]:
    """(offset, opcode, length) of every top-level record of the intact file."""
    out = []
    f = io.BytesIO(data)
    reader = StreamReader(f, skip_magic=False, emit_chunks=True)
    pos = 8
    for _ in reader.records:
        end = f.tell()
        out.append((pos, data[pos], end - pos - 9))
        pos = end
    return out


def variants(data: bytes, n: int) -> list[tuple[str, bytes]]:
    """Deterministic corruptions: byte flips at structural and random offsets, and truncations."""
    offsets: list[int] = [0, 3, 7, len(data) - 1, len(data) - 8]
    for pos, op, length in record_offsets(data):
        offsets += [pos, pos + 1, pos + 8, pos + 9, pos + 9 + length // 2, pos + 9 + max(length - 1, 0)]
        if op == 0x06:  # chunk: start/end time, uncompressed size, crc, compression, records length, data
            offsets += [pos + 9 + 16, pos + 9 + 24, pos + 9 + 28, pos + 9 + 32, pos + 9 + 36, pos + 9 + 40,
                        pos + 9 + 44]
            offsets += [pos + 9 + 52 + k * (length - 60) // 6 for k in range(6)]
    rng = random.Random(16)
    offsets = sorted({o for o in offsets if 0 <= o < len(data)})
    picked = offsets if len(offsets) <= n * 3 // 4 else sorted(rng.sample(offsets, n * 3 // 4))
    out = []
    for o in picked:
        b = bytearray(data)
        b[o] ^= 0xFF
        out.append((f"flip@{o}", bytes(b)))
    while len(out) < n - 12:
        o = rng.randrange(len(data))
        b = bytearray(data)
        b[o] ^= 1 << rng.randrange(8)
        out.append((f"bit@{o}", bytes(b)))
    for k in range(12):  # torn files (a crash while writing), including inside the summary
        cut = (k + 1) * len(data) // 13
        out.append((f"cut@{cut}", data[:cut]))
    return out[:n]


def _info(args: list[str]) -> tuple[int, str]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        code = info.main(args)
    return code, out.getvalue()


@pytest.mark.timeout(1200)
def test_no_tool_reads_fewer_messages_than_the_mcap_reader_from_a_corrupted_sample(tmp_path):
    data = FILE.read_bytes()
    total = independent_count(FILE)
    assert total == SAMPLE_MESSAGES
    rows = []
    worse = []
    repaired = 0
    for k, (name, blob) in enumerate(variants(data, VARIANTS)):
        bag = tmp_path / f"v{k}"
        bag.mkdir()
        shutil.copy(SAMPLE / "metadata.yaml", bag / "metadata.yaml")
        path = bag / "sample_0.mcap"
        path.write_bytes(blob)
        digest = hashlib.sha256(blob).hexdigest()
        code, text = _info([str(bag), "--json"])  # the reader, through info
        assert code in (0, 1), (name, text)
        report = json.loads(text)
        ours = sum(report["counts"].values())
        if code == 0:
            assert ours == total and report["state"] == "closed", (name, ours, report["damage"])
        else:
            assert report["state"] in ("damaged", "unclosed") and (ours == total or report["damage"]), name
        # the independent readers cannot read more than all: compare whenever we lost any, and every 4th
        theirs = independent_count(path) if ours < total or k % 4 == 0 else None
        if theirs is not None and ours < theirs:
            worse.append((name, ours, theirs))
        if k % 4 == 0 or ours < total:
            out = tmp_path / f"v{k}.repaired"
            code, text = _info([str(bag), "--repair"])
            assert code == 0, (name, text)
            assert hashlib.sha256(path.read_bytes()).hexdigest() == digest, f"{name}: repair changed the original"
            if out.exists():
                copy = bagfile.scan(out)
                assert copy.state == "repaired" and sum(copy.counts.values()) == ours, (name, copy.report())
                assert dict(copy.counts) == report["counts"]
                assert independent_count(out / "sample_0.mcap", seeking_only=True) == ours, name
                assert "dropped:" in text
                shutil.rmtree(out)
                repaired += 1
            else:
                assert code == 0 and ours == total, name
        rows.append((name, theirs, ours))
        shutil.rmtree(bag)
    assert not worse, f"read fewer messages than the mcap reader: {worse[:10]}"
    compared = [(t, o) for _, t, o in rows if t is not None]
    print(f"{len(rows)} variants: never fewer messages than mcap's best reader ({len(compared)} compared: more in "
          f"{sum(o > t for t, o in compared)}, mcap short of all {total} in {sum(t < total for t, _ in compared)}); "
          f"ours short of all in {sum(o < total for _, _, o in rows)}; {repaired} repaired copies checked")


@pytest.mark.parametrize("spot", ["crc", "data", "length", "summary"])
def test_info_cli_on_a_damaged_closed_bag_says_damaged_and_skips_on(tmp_path, spot):
    """One damaged chunk of a closed bag: the CLI reads every other chunk, says DAMAGED (not NOT
    CLOSED), exits 1, prints no traceback, and ``--repair`` writes a copy holding all of it."""
    data = bytearray(FILE.read_bytes())
    chunks = [(p, n) for p, op, n in record_offsets(bytes(data)) if op == 0x06]
    pos, length = chunks[2]
    where = {"crc": pos + 9 + 24, "data": pos + 9 + 60 + length // 3, "length": pos + 5,
             "summary": len(data) - 200}[spot]
    data[where] ^= 0xFF
    bag = tmp_path / "bag"
    bag.mkdir()
    shutil.copy(SAMPLE / "metadata.yaml", bag / "metadata.yaml")
    (bag / "sample_0.mcap").write_bytes(bytes(data))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "bags"), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-m", "nf_bags.info", str(bag)], capture_output=True, text=True,
                          env=env, timeout=120)
    assert "Traceback" not in done.stderr + done.stdout
    assert done.returncode == 1 and "DAMAGED" in done.stdout and "NOT CLOSED" not in done.stdout, done.stdout
    ours = sum(bagfile.scan(bag).counts.values())
    assert ours >= independent_count(bag / "sample_0.mcap")
    if spot in ("crc", "length", "summary"):
        assert ours == SAMPLE_MESSAGES  # the messages are intact: only a field around them is damaged
    else:
        assert ours >= SAMPLE_MESSAGES - sum(1 for _ in _chunk_messages(bytes(data), pos))
    done = subprocess.run([sys.executable, "-m", "nf_bags.info", str(bag), "--repair"], capture_output=True,
                          text=True, env=env, timeout=120)
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr
    assert "dropped:" in done.stdout and (bag / "sample_0.mcap").read_bytes() == bytes(data)
    repaired = bagfile.scan(tmp_path / "bag.repaired")
    assert repaired.state == "repaired" and sum(repaired.counts.values()) == ours, repaired.report()


def _chunk_messages(data: bytes, pos: int) -> list[int]:
    """Message indexes of the chunk at ``pos`` in the intact sample (to bound a damaged chunk's loss)."""
    f = io.BytesIO(FILE.read_bytes())
    f.seek(pos)
    reader = StreamReader(f, skip_magic=True, emit_chunks=True)
    from mcap.stream_reader import breakup_chunk

    chunk = next(iter(reader.records))
    return [1 for r in breakup_chunk(chunk) if type(r).__name__ == "Message"]
