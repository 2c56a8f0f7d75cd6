"""Crash-loss accounting (issue 16, item 11): a real recorder process recording a real publisher
(std_msgs/Header at 500 Hz, stamp = publish time, frame_id = sequence number) is killed with
SIGKILL at several moments, one before its first chunk. For every run:

- the loss ``info`` counts is a lower bound of the real loss (messages published after the last
  readable one and before the kill);
- the README's promise holds: nothing published more than ``--chunk-seconds`` (plus the recorder's
  own lag behind the publisher, measured on the readable messages) before the kill is lost;
- the reported end of the loss (``loss_bound``) is not before the kill, give or take that lag.
"""

from __future__ import annotations

import json
import signal
import time
from pathlib import Path

import pytest
from nf_bags import bagfile
from test_bags_latched import bag_domain_id

from ros_testing import RosProcess

pytestmark = pytest.mark.ros

# argv[1]: file of "seq publish_ns" lines; argv[2]: s to run
PUBLISHER = """
import sys, time, rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import Header
rclpy.init()
node = rclpy.create_node("stamps")
pub = node.create_publisher(Header, "/stamps", QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
out = open(sys.argv[1], "w")
end = time.monotonic() + float(sys.argv[2])
seq, due = 0, time.monotonic()
print("publishing", flush=True)
while time.monotonic() < end:
    t = time.time_ns()
    msg = Header(frame_id=str(seq))
    msg.stamp.sec, msg.stamp.nanosec = divmod(t, 1_000_000_000)
    pub.publish(msg)
    out.write(f"{seq} {t}\\n")
    if seq % 50 == 0:
        out.flush()
    seq += 1
    due += 0.002
    time.sleep(max(0.0, due - time.monotonic()))
out.close()
"""
CHUNK = 1.0  # the recorder's defaults: chunks every 1 s, metadata every 0.5 s
KILL_AFTER = (0.4, 1.3, 2.2, 3.1)  # s after the recorder subscribed; the first is before any chunk


def _wait(predicate, timeout: float) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end and not predicate():
        time.sleep(0.01)
    return predicate()


def _published(path: Path) -> dict[int, int]:
    out = {}
    for line in path.read_text().splitlines():
        parts = line.split()
        if len(parts) == 2:
            out[int(parts[0])] = int(parts[1])
    return out


@pytest.mark.parametrize("delay", KILL_AFTER)
def test_kill_9_loss_report_is_an_honest_bound(tmp_path, delay):
    domain = bag_domain_id()
    bag = tmp_path / "bag"
    pub = RosProcess(["-c", PUBLISHER, str(tmp_path / "published.txt"), "120"], domain, tmp_path / "pub.log")
    rec = None
    try:
        assert _wait(lambda: "publishing" in pub.log(), 60), pub.log()
        rec = RosProcess(["-m", "nf_bags.record", "-o", str(bag), "--topics", "/stamps"], domain,
                         tmp_path / "recorder.log")
        assert _wait(lambda: "recording /stamps (" in rec.log(), 60), rec.log()
        subscribed = time.time_ns()
        time.sleep(delay)
        rec.proc.send_signal(signal.SIGKILL)
        killed = time.time_ns()
        rec.proc.wait(10)
        time.sleep(0.3)
    finally:
        pub.stop()
        if rec is not None:
            rec.stop()
    published = _published(tmp_path / "published.txt")
    health = bagfile.scan(bag)
    assert health.state == "unclosed", health.report()
    readable = {}
    lag = 0.0
    from nf_bags import reader

    for d in reader.read_messages(bag, ["/stamps"]):
        seq = int(d.msg.frame_id)
        readable[seq] = d.log_time
        lag = max(lag, (d.log_time - reader.stamp_ns(d.msg)) * 1e-9)
    allowance = lag + 0.05  # the recorder's measured lag behind the publisher, plus scheduling
    last = max(readable, default=-1)
    lost = {s: t for s, t in published.items() if s > last and (last >= 0 or t >= subscribed) and t <= killed}
    bound = health.loss_bound()
    assert bound is not None
    # 1. what info counts is really lost
    assert bound["lost_at_least"] <= len(lost), (bound, len(lost))
    # 2. the promise: only the open chunk (< CHUNK s of receive time), plus what the recorder had not taken yet
    oldest = min(lost.values(), default=killed)
    assert (killed - oldest) * 1e-9 <= CHUNK + allowance, ((killed - oldest) * 1e-9, allowance, health.report())
    # 3. the reported end of the loss covers the kill
    if bound["lost_until_ns"] is not None:
        assert killed <= bound["lost_until_ns"] + allowance * 1e9, (bound, killed, health.report())
    else:
        assert bound["lost_at_least"] == 0 and not readable
    report = health.report()
    assert "NOT CLOSED" in report and f"at least {bound['lost_at_least']} messages" in report
    info = RosProcess(["-m", "nf_bags.info", str(bag), "--json"], domain, tmp_path / "info.log")
    assert info.proc.wait(60) == 1, info.log()
    assert json.loads(info.log())["loss_bound"]["lost_at_least"] == bound["lost_at_least"]
    print(f"kill after {delay} s: {len(readable)} readable, {len(lost)} really lost "
          f"({(killed - oldest) * 1e-9:.3f} s before the kill), {bound['lost_at_least']} counted; "
          f"reported end {((bound['lost_until_ns'] or killed) - killed) * 1e-9:+.3f} s from the kill "
          f"({'guaranteed' if bound['guaranteed'] else 'if timers on time'}); recorder lag {lag * 1e3:.1f} ms")
