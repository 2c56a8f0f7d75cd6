"""The shipped learner configs learn what they learned before the settings were reshaped: 2 in-process
iterations of each (metrics, evaluation, final weights) equal the stored fingerprints to 1e-9."""

from __future__ import annotations

import json

import fingerprint
import pytest


@pytest.mark.parametrize("name", list(fingerprint.RUNS))
def test_shipped_config_learns_as_its_fingerprint(name):
    stored = json.loads((fingerprint.FOLDER / f"{name}.json").read_text())
    diff = fingerprint.differences(stored, fingerprint.compute(name))
    assert not diff, f"{name} ({' + '.join(fingerprint.RUNS[name])}) changed:\n" + "\n".join(diff[:20])


def test_the_comparison_sees_a_change():
    stored = {"metrics": [{"success_rate": 0.4, "return_mean": -100.0}], "weights": {"w": [1.0, 2.0]}}
    assert not fingerprint.differences(stored, json.loads(json.dumps(stored)))
    assert fingerprint.differences(stored, {"metrics": [{"success_rate": 0.4, "return_mean": -100.0 + 1e-6}],
                                            "weights": {"w": [1.0, 2.0]}})
    assert fingerprint.differences(stored, {"metrics": stored["metrics"], "weights": {"w": [1.0]}})
