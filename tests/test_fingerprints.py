"""The shipped learner configs learn what they learned before the settings were reshaped: 2 in-process
iterations of each (metrics, evaluation, final weights) equal the stored fingerprints of this kind of
CPU to 1e-9 (tests/fingerprint.py says why the kind matters)."""

from __future__ import annotations

import fingerprint
import pytest


@pytest.mark.parametrize("name", list(fingerprint.RUNS))
def test_shipped_config_learns_as_its_fingerprint(name):
    cpu, stored = fingerprint.machine(), fingerprint.stored(name)
    actual = fingerprint.compute(name)
    if cpu in stored:
        diff = fingerprint.differences(stored[cpu], actual)
        assert not diff, f"{name} ({' + '.join(fingerprint.RUNS[name])}) changed on {cpu}:\n" + "\n".join(diff[:20])
        return
    alike = [kind for kind, fp in stored.items() if not fingerprint.differences(fp, actual)]
    if not alike:  # another kind of CPU, or a change: only a fingerprint written here at a known-good commit tells
        pytest.skip(f"no fingerprint of {name} for this CPU ({cpu}), and none of {sorted(stored)} computes alike: "
                    "write this CPU's at a known-good commit with `python tests/fingerprint.py --write`")


def test_the_comparison_sees_a_change():
    stored = {"metrics": [{"success_rate": 0.4, "return_mean": -100.0}], "weights": {"w": [1.0, 2.0]}}
    assert not fingerprint.differences(stored, {"metrics": [{"success_rate": 0.4, "return_mean": -100.0}],
                                                "weights": {"w": [1.0, 2.0]}})
    assert fingerprint.differences(stored, {"metrics": [{"success_rate": 0.4, "return_mean": -100.0 + 1e-6}],
                                            "weights": {"w": [1.0, 2.0]}})
    assert fingerprint.differences(stored, {"metrics": stored["metrics"], "weights": {"w": [1.0]}})


def test_this_cpu_has_a_name_and_every_stored_kind_has_every_run():
    assert fingerprint.machine()
    for name in fingerprint.RUNS:
        assert fingerprint.stored(name), f"no stored fingerprint of {name}"
    kinds = {kind for name in fingerprint.RUNS for kind in fingerprint.stored(name)}
    for kind in kinds:
        missing = [n for n in fingerprint.RUNS if kind not in fingerprint.stored(n)]
        assert not missing, f"{kind}: no fingerprint of {missing}"
