"""The learner's chunk collector: a waiter wakes when the last chunk of its episode arrives, not by polling."""

from __future__ import annotations

import threading
import time
from types import SimpleNamespace

from learner_node.ros_episodes import ChunkCollector


def test_wait_for_wakes_on_the_last_chunk_and_times_out_otherwise():
    chunks = ChunkCollector()
    assert not chunks.wait_for(7, 1, 0.05)  # nothing arrives: False after the timeout

    def deliver() -> None:
        for seq in range(3):
            time.sleep(0.02)
            chunks.add(SimpleNamespace(episode_id=7 if seq != 1 else 8, seq=seq))
        time.sleep(0.02)
        chunks.add(SimpleNamespace(episode_id=7, seq=3))

    sender = threading.Thread(target=deliver)
    t0 = time.monotonic()
    sender.start()
    assert chunks.wait_for(7, 3, 5.0)  # the third chunk of episode 7 (one of episode 8 between)
    waited = time.monotonic() - t0
    sender.join()
    assert chunks.count(7) == 3 and chunks.count(8) == 1
    assert waited < 1.0, waited
    assert [c.seq for c in chunks.pop(7)] == [0, 2, 3]
