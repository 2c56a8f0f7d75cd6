"""Bad input to the bag tools (no ROS graph): missing or unsupported bags and broken metadata.yaml
give one clear error line and exit 2, never a traceback or "closed cleanly" (issue 16, item 10);
foreign bags for resim, play and the reader give clear errors (item 12); the writer's metadata
follows rosbag2 Jazzy (item 13)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from nf_bags import bagfile, reader, resim
from nf_bags.record import message_class
from nf_bags.writer import BagWriter, WriterConfig, qos_dict

from ros_testing import REPO, ros_env

SAMPLE = REPO / "bags" / "sample"


def run_tool(*args: str) -> subprocess.CompletedProcess:
    """``python -m <args>`` with nf_bags importable; a ROS domain of this test range, loopback only."""
    env = ros_env(int(os.environ.get("ROS_DOMAIN_ID") or 66))
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, env=env, timeout=180)


def assert_clean_error(done: subprocess.CompletedProcess, *words: str) -> None:
    out = done.stdout + done.stderr
    assert "Traceback" not in out, out
    assert done.returncode == 2, (done.returncode, out)
    assert "closed cleanly" not in out
    assert done.stderr.startswith("error: "), out
    for w in words:
        assert w in done.stderr, (w, done.stderr)


def _bag_copy(tmp_path: Path) -> Path:
    bag = tmp_path / "bag"
    shutil.copytree(SAMPLE, bag)
    return bag


@pytest.fixture(scope="module")
def broken_bags(tmp_path_factory) -> dict[str, tuple[Path, tuple[str, ...]]]:
    tmp = tmp_path_factory.mktemp("broken")
    out: dict[str, tuple[Path, tuple[str, ...]]] = {"missing": (tmp / "nonexistent", ("does not exist",))}
    b = tmp / "missing_mcap"
    shutil.copytree(SAMPLE, b)
    (b / "sample_0.mcap").unlink()
    out["missing_mcap"] = (b, ("sample_0.mcap", "missing"))
    b = tmp / "sqlite"
    b.mkdir()
    meta = yaml.safe_load((SAMPLE / "metadata.yaml").read_text())
    meta["rosbag2_bagfile_information"]["storage_identifier"] = "sqlite3"
    meta["rosbag2_bagfile_information"]["relative_file_paths"] = ["sqlite_0.db3"]
    (b / "metadata.yaml").write_text(yaml.safe_dump(meta))
    (b / "sqlite_0.db3").write_bytes(b"SQLite format 3\x00" + bytes(100))
    out["sqlite"] = (b, ("sqlite3", "MCAP"))
    out["sqlite_file"] = (b / "sqlite_0.db3", ("sqlite3",))
    b = tmp / "invalid_yaml"
    shutil.copytree(SAMPLE, b)
    (b / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 9\n  topics: [unclosed\n")
    out["invalid_yaml"] = (b, ("metadata.yaml", "YAML"))
    b = tmp / "truncated_yaml"
    shutil.copytree(SAMPLE, b)
    text = (SAMPLE / "metadata.yaml").read_text()
    (b / "metadata.yaml").write_text(text[:200])
    out["truncated_yaml"] = (b, ("metadata.yaml",))
    b = tmp / "empty_dir"
    b.mkdir()
    out["empty_dir"] = (b, ("not a bag",))
    return out


@pytest.mark.parametrize("case", ["missing", "missing_mcap", "sqlite", "sqlite_file", "invalid_yaml",
                                  "truncated_yaml", "empty_dir"])
def test_info_and_reader_refuse_missing_or_unsupported_bags_with_a_clear_error(broken_bags, case):
    bag, words = broken_bags[case]
    assert_clean_error(run_tool("nf_bags.info", str(bag)), *words)
    with pytest.raises(bagfile.BagError):
        list(bagfile.iter_raw(bag))
    with pytest.raises(bagfile.BagError):
        bagfile.scan(bag)


def test_reader_and_resim_clis_give_clear_errors_for_missing_bags(broken_bags):
    bag, words = broken_bags["missing"]
    assert_clean_error(run_tool("nf_bags.reader", str(bag)), *words)
    assert_clean_error(run_tool("nf_bags.resim", str(bag)), *words)


def _subset_bag(path: Path, topics: set[str], rename: dict[str, str] | None = None) -> Path:
    """A bag with only ``topics`` of the sample (types renamed by ``rename``, e.g. to foreign ones)."""
    rename = rename or {}
    w = BagWriter(path, WriterConfig())
    for m in bagfile.iter_raw(SAMPLE, topics):
        if m.topic not in w.topics:
            w.add_topic(m.topic, rename.get(m.type, m.type), m.schema.data.decode())
        w.write(m.topic, m.data, m.log_time)
    w.close()
    return path


def _foreign_encoding_file(path: Path, encoding: str) -> Path:
    """One .mcap file with the sample's /task_status under another message encoding."""
    from mcap.writer import Writer

    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="test")
        ids: dict[str, int] = {}
        for m in bagfile.iter_raw(SAMPLE, ["/task_status"]):
            if m.topic not in ids:
                sid = w.register_schema(m.schema.name, m.schema.encoding, m.schema.data)
                ids[m.topic] = w.register_channel(m.topic, encoding, sid)
            w.add_message(ids[m.topic], m.log_time, m.data, m.log_time)
        w.finish()
    return path


def test_resim_on_a_bag_without_reset_states_or_episodes_says_so(tmp_path):
    bag = _subset_bag(tmp_path / "rollouts_only", {"/rollouts", "/task_status"})
    done = run_tool("nf_bags.resim", str(bag))
    assert_clean_error(done, "no reset state")
    done = run_tool("nf_bags.resim", str(SAMPLE), "--episode", "5")
    assert_clean_error(done, "episode 5 does not exist", "2 reset states")
    done = run_tool("nf_bags.resim", str(SAMPLE), "--start-ns", "123")
    assert_clean_error(done, "no recorded reset state at 123")
    # a bag whose joint states have their resets but no lockstep command answers them
    bag = _subset_bag(tmp_path / "states_only", {"/joint_states", "/task_status"})
    assert_clean_error(run_tool("nf_bags.resim", str(bag), "--episode", "1"), "nothing to re-simulate")


def test_resim_policy_says_why_it_cannot_rebuild_an_episode(broken_bags, tmp_path):
    assert_clean_error(run_tool("nf_bags.resim_policy", str(broken_bags["missing"][0])), *broken_bags["missing"][1])
    # the sample's policy messages predate the law fields: its policy cannot be run again as it was
    assert_clean_error(run_tool("nf_bags.resim_policy", str(SAMPLE)), "cannot be rebuilt", "potential_force_bound")
    # joint states without rollouts: nothing to re-simulate in closed loop
    bag = _subset_bag(tmp_path / "states_only", {"/joint_states", "/task_status"})
    assert_clean_error(run_tool("nf_bags.resim_policy", str(bag)), "no complete episode")


def test_message_class_names_bad_type_names_and_play_refuses_them(tmp_path):
    with pytest.raises(ValueError, match="not a message type name"):
        message_class("Foo")
    with pytest.raises(ValueError, match="not a message type name"):
        message_class("a/b/c/d")
    with pytest.raises(LookupError, match="not installed"):
        message_class("no_such_pkg/msg/Thing")
    with pytest.raises(LookupError, match="has no message"):
        message_class("std_msgs/msg/NoSuchType")
    assert message_class("std_msgs/String").__name__ == "String"
    bag = _subset_bag(tmp_path / "foreign", {"/rollouts"}, {"nf_msgs/msg/RolloutChunk": "zz_msgs/msg/RolloutChunk"})
    done = run_tool("nf_bags.play", str(bag), "--fast", "--wait", "0")
    assert_clean_error(done, "/rollouts", "zz_msgs/msg/RolloutChunk", "not installed")
    bag = _subset_bag(tmp_path / "short", {"/rollouts"}, {"nf_msgs/msg/RolloutChunk": "RolloutChunk"})
    done = run_tool("nf_bags.play", str(bag), "--fast", "--wait", "0")
    assert_clean_error(done, "/rollouts", "not a message type name: 'RolloutChunk'")


def test_read_messages_names_the_message_encoding_it_cannot_decode(tmp_path):
    path = _foreign_encoding_file(tmp_path / "json.mcap", "json")
    assert sum(1 for _ in bagfile.iter_raw(path)) == 76
    with pytest.raises(ValueError, match="message encoding 'json' with schema encoding 'ros2msg'"):
        next(reader.read_messages(path))


def test_writer_metadata_infinite_durations_and_closed_state_embedded_in_the_mcap(tmp_path):
    class Qos:
        history = reliability = durability = liveliness = "x"
        depth = 1
        avoid_ros_namespace_conventions = False

        class deadline:  # noqa: N801 - rclpy Duration stand-ins
            nanoseconds = 2**63 - 1

        lifespan = liveliness_lease_duration = deadline

    entry = qos_dict(Qos())
    infinite = {"sec": 9223372036, "nsec": 854775807}  # RMW_DURATION_INFINITE as rosbag2 Jazzy writes it
    assert entry["deadline"] == entry["lifespan"] == entry["liveliness_lease_duration"] == infinite
    bag = _subset_bag(tmp_path / "closed", {"/rollouts"})
    with open(bag / "closed_0.mcap", "rb") as f:
        records = {name: meta for name, meta in ((m.name, m.metadata) for m in make_reader(f).iter_metadata())}
    info = yaml.safe_load(records["rosbag2"]["serialized_metadata"])
    assert info["custom_data"]["nf_bags.state"] == "closed"
    assert info["message_count"] == 2 and info["version"] == 9
    assert bagfile.load_metadata(bag)["custom_data"]["nf_bags.state"] == "closed"


def test_resim_of_a_thinned_recording_names_the_gap_instead_of_comparing_wrong_states(tmp_path):
    """A composed sim with monitor_period > 0 records every N-th state and command: re-simulation
    must stop at the first gap and say why, never compare one step with a state N steps later."""
    start = resim.episode_starts(SAMPLE)[1]
    stamps = reader.joint_trajectory(SAMPLE).stamp_ns
    drop = int(stamps[np.flatnonzero(stamps == start)[0] + 1])  # the state right after the reset
    path = tmp_path / "thinned"
    w = BagWriter(path, WriterConfig())
    for d in reader.read_messages(SAMPLE, {"/joint_states", "/effort_controller/commands", "/task_status"}):
        m = d.raw
        if m.topic not in w.topics:
            w.add_topic(m.topic, m.type, m.schema.data.decode())
        if m.topic == "/joint_states" and reader.stamp_ns(d.msg.header) == drop:
            continue
        w.write(m.topic, m.data, m.log_time)
    w.close()
    assert len(reader.joint_trajectory(path).stamp_ns) == len(stamps) - 1
    assert_clean_error(run_tool("nf_bags.resim", str(path), "--episode", "1"), "nothing to re-simulate",
                       "2000000 ns gap", "monitor_period")
