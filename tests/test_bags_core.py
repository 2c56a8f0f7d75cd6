"""The bag code without a ROS graph: schemas, the writer's chunks, splits and metadata, reading a
torn file and repairing it, and the committed sample bag (bags/sample, `python -m nf_bringup.sample_bag`)
read by two readers, summarised and re-simulated exactly."""

from __future__ import annotations

import shutil
import threading
from collections import defaultdict
from pathlib import Path

import pytest
from nf_bags import bagfile, reader, resim
from nf_bags.bagfile import BagError
from nf_bags.play import read_ahead
from nf_bags.schemas import message_definition
from nf_bags.writer import BagWriter, WriterConfig
from rosbags.highlevel import AnyReader
from rosbags.typesys import get_types_from_msg

from ros_testing import REPO

SAMPLE = REPO / "bags" / "sample"


@pytest.fixture(scope="module")
def sample_messages() -> list[bagfile.RawMessage]:
    return list(bagfile.iter_raw(SAMPLE))


def test_schema_text_has_every_nested_type_once_and_parses():
    text = message_definition("nf_msgs/msg/RolloutChunk")
    assert text.startswith("# A piece of one episode's rollout")
    assert [line for line in text.splitlines() if line.startswith("MSG: ")] == [
        "MSG: std_msgs/Header", "MSG: builtin_interfaces/Time"]
    types = get_types_from_msg(text, "nf_msgs/msg/RolloutChunk")
    assert {"nf_msgs/msg/RolloutChunk", "std_msgs/msg/Header", "builtin_interfaces/msg/Time"} <= set(types)
    diag = message_definition("diagnostic_msgs/msg/DiagnosticArray")
    assert diag.count("MSG: ") == 4  # Header, DiagnosticStatus, Time, KeyValue


def test_sample_bag_is_small_closed_and_reads_equal_through_two_readers(sample_messages):
    assert sum(f.stat().st_size for f in SAMPLE.iterdir()) < 2_000_000
    health = bagfile.scan(SAMPLE)
    assert health.closed and not health.lost, health.report()
    first = defaultdict(list)
    for d in reader.read_messages(SAMPLE):
        first[d.topic].append(reader.as_plain(d.msg))
    second = defaultdict(list)
    with AnyReader([SAMPLE]) as r:
        for conn, _, raw in r.messages():
            second[conn.topic].append(reader.as_plain(r.deserialize(raw, conn.msgtype)))
    assert first.keys() == second.keys() and len(sample_messages) == sum(map(len, first.values()))
    for topic in first:
        assert all(reader.same(a, b) for a, b in zip(first[topic], second[topic], strict=True)), topic


def test_sample_bag_summary_episode_and_exact_resimulation(tmp_path):
    summary = reader.summarize(SAMPLE)
    assert summary["resets"] == 2 and len(summary["episodes"]) == 1 and summary["episodes"][0]["complete"]
    records = reader.episode_records(SAMPLE)
    assert len(records) == 1 and len(records[0].reward) == summary["episodes"][0]["decisions"]
    r = resim.resimulate(SAMPLE, resim.episode_starts(SAMPLE)[1])
    assert r.steps >= 1000 and r.max_error <= 1e-9 and r.max_effort_error <= 1e-9, r
    assert reader.plot_run(SAMPLE, tmp_path / "run.png").stat().st_size > 10_000


class FakeClock:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def _copy_messages(messages, bag: Path, config: WriterConfig, clock=None, spacing_ns: int | None = None
                   ) -> BagWriter:
    """A bag of ``messages`` (received ``spacing_ns`` apart if given, else at their recorded times)."""
    writer = BagWriter(bag, config, **({"clock": clock} if clock else {}))
    t0 = messages[0].log_time
    for i, m in enumerate(messages):
        if m.topic not in writer.topics:
            writer.add_topic(m.topic, m.type, m.schema.data.decode())
        writer.write(m.topic, m.data, m.log_time if spacing_ns is None else t0 + i * spacing_ns)
    return writer


def test_writer_chunks_by_time_and_size_splits_files_and_keeps_metadata_current(sample_messages, tmp_path):
    clock = FakeClock()
    writer = _copy_messages(sample_messages[:100], tmp_path / "a", WriterConfig(chunk_bytes=1 << 30), clock, 1_000_000)
    assert writer.chunks == 0
    meta = bagfile.load_metadata(tmp_path / "a")
    assert meta["message_count"] < 100  # written at start and per new topic; counts come with the next update
    clock.t = 0.6
    writer.tick()  # metadata due (0.5 s), chunk not yet (1 s)
    assert writer.chunks == 0 and bagfile.load_metadata(tmp_path / "a")["message_count"] == 100
    assert bagfile.scan(tmp_path / "a").counts.total() == 0  # nothing on disk yet: the open chunk
    clock.t = 1.1
    writer.tick()
    assert writer.chunks == 1 and bagfile.scan(tmp_path / "a").counts.total() == 100
    writer.close()

    split = _copy_messages(sample_messages, tmp_path / "b", WriterConfig(chunk_bytes=20_000, split_bytes=150_000))
    split.close()
    health = bagfile.scan(tmp_path / "b")
    assert len(health.files) >= 3 and health.closed
    assert [m.data for m in bagfile.iter_raw(tmp_path / "b")] == [m.data for m in sample_messages]
    meta = bagfile.load_metadata(tmp_path / "b")
    assert sum(f["message_count"] for f in meta["files"]) == meta["message_count"] == len(sample_messages)
    with AnyReader([tmp_path / "b"]) as r:
        assert sum(1 for _ in r.messages()) == len(sample_messages)


def test_torn_file_reads_to_its_last_complete_chunk_and_repairs(sample_messages, tmp_path):
    bag = tmp_path / "torn"
    writer = _copy_messages(sample_messages, bag, WriterConfig(chunk_bytes=30_000))
    writer.write_metadata()
    writer.flush()
    assert writer.chunks > 5
    # a recorder killed while writing a chunk: no summary, the file ends in the middle of a record
    path = writer.files[-1].path
    writer._stream.flush()
    size = path.stat().st_size
    shutil.copy(path, tmp_path / "whole.mcap")
    with open(path, "r+b") as f:
        f.truncate(size - 1000)
    health = bagfile.scan(bag)
    assert not health.closed and not health.files[0].complete and health.files[0].torn_bytes > 0
    readable = [m.data for m in bagfile.iter_raw(bag)]
    assert 0 < len(readable) < len(sample_messages)
    assert readable == [m.data for m in sample_messages[:len(readable)]], "a prefix, nothing out of order"
    assert sum(health.lost.values()) == len(sample_messages) - len(readable)
    assert "NOT CLOSED" in health.report()
    torn_bytes = path.read_bytes()
    result = bagfile.repair(bag)
    # a repaired copy next to the original, which stays as it was; the report says what was dropped
    assert result.output == tmp_path / "torn.repaired" and path.read_bytes() == torn_bytes
    assert result.messages == len(readable) and any("torn bytes" in d for d in result.dropped), result.report()
    repaired = bagfile.scan(result.output)
    assert repaired.state == "repaired" and [m.data for m in bagfile.iter_raw(result.output)] == readable
    assert f"the original lost {len(sample_messages) - len(readable)} messages counted" in repaired.report()
    with AnyReader([result.output]) as r:
        assert sum(1 for _ in r.messages()) == len(readable)
    with pytest.raises(bagfile.BagError, match="exists"):
        bagfile.repair(bag)  # never over an earlier copy


def test_chunks_never_span_chunk_seconds_of_receive_time_even_when_the_timer_is_late(sample_messages, tmp_path):
    """A kill loses at most the open chunk: the writer cuts chunks by the messages' receive times,
    so a late (or never running) tick cannot let one grow past ``chunk_seconds`` (issue 16, item 11)."""
    clock = FakeClock()  # never advances: the recorder's timers do not run
    bag = tmp_path / "late"
    writer = _copy_messages(sample_messages[:400], bag, WriterConfig(chunk_bytes=1 << 30, chunk_seconds=1.0),
                            clock, spacing_ns=10_000_000)  # 4 s of messages, 10 ms apart
    assert writer.chunks == 3
    writer.write_metadata()
    meta = bagfile.load_metadata(bag)
    pending = int(meta["custom_data"]["nf_bags.pending_since_ns"])
    assert pending == sample_messages[0].log_time + 300 * 10_000_000  # the open chunk's first message
    # as if killed now: every message received more than chunk_seconds before the last one is readable
    health = bagfile.scan(bag)
    assert health.counts.total() == 300 and health.state == "unclosed"
    bound = health.loss_bound()
    assert bound["lost_at_least"] == 100 and bound["guaranteed"]
    assert bound["lost_until_ns"] == pending + 1_000_000_000
    writer.close()


def test_player_reads_ahead_in_order_and_hands_over_a_read_error(sample_messages):
    """The replay's messages come from a read-ahead thread (a timed replay must not decode a chunk
    while a message is due): same order, a reader's error raised in the player, a stop honoured."""
    stop = threading.Event()
    ahead = list(read_ahead(bagfile.iter_raw(SAMPLE), stop, depth=7))
    assert [m.data for m in ahead] == [m.data for m in sample_messages]

    def broken():
        yield sample_messages[0]
        raise BagError("torn chunk")

    got = []
    with pytest.raises(BagError, match="torn chunk"):
        for raw in read_ahead(broken(), stop):
            got.append(raw)
    assert len(got) == 1
    stop.set()
    assert list(read_ahead(iter(sample_messages), stop)) == []


@pytest.mark.ros
def test_a_bag_of_an_arm_with_joint_friction_resimulates_exactly_with_that_friction_only(tmp_path):
    """The bag does not hold the arm's friction: re-simulated without it the arm goes elsewhere, with it given
    the same states to 1e-9. nf_bags.info says the bag can be re-simulated."""
    from nf_bags.info import main as info_main

    from nf_bringup.sample_bag import record_sample

    bag = record_sample(tmp_path / "friction", duration=0.6, sim_args=["-p", "joint_friction:=0.4",
                                                                       "-p", "joint_viscous:=0.05"])
    start = resim.episode_starts(bag)[1]
    plain = resim.resimulate(bag, start)
    assert plain.steps >= 500 and plain.max_q_error > 1e-6, plain
    exact = resim.resimulate(bag, start, friction=(0.4, 0.05))
    assert exact.steps == plain.steps and exact.max_error <= 1e-9 and exact.max_effort_error <= 1e-9, exact
    assert resim.resimulable(bag)[0] and resim.resimulable(bag)[1].startswith("every 1 ms state")
    assert info_main([str(bag)]) == 0
