"""Code, configs and reference docs say what things are; results and their history live in
docs/results and docs/measurements.md. This check finds dates, issue numbers and measured results
where they do not belong."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("nf_core", "learner_node", "nf_controller_node", "sim_bridge_node", "franka_driver", "nf_bringup",
            "bags", "msgs")
SUFFIXES = {".py", ".yaml", ".msg", ".srv", ".action", ".md", ".xml", ".cfg", ".txt"}
REFERENCE_DOCS = ("docs/controller.md", "docs/nodes.md", "docs/simulation.md", "docs/fleet.md", "docs/teach.md",
                  "docs/hardware.md", "bags/README.md")
PATTERNS = {
    "a date": re.compile(r"\b20[0-9]{2}-[01][0-9]-[0-3][0-9]\b"),
    "an issue number": re.compile(r"(?i)\bissues? #?[0-9]+\b|(?<![\w&/'\"])#[0-9]+\b|\b(?:session|stop) [0-9]+\b"),
    "a measured result": re.compile(
        r"(?i)\bmeasured\b[^.;\n]*?\b[0-9]+(?:\.[0-9]+)?\b(?! ?(?:m|mm|s|ms|Hz|N|Nm|rad)\b)"
        r"|\b(?:90 % )?windows? (?:at |of )?[0-9]+\b"
        r"|\b[0-9]+ ?(?:/|of) ?[0-9]+ (?:held-out|starts|seeds|episodes|rollouts) (?:insert|succeed|transfer)"
        r"|\binstead of [0-9]"
        r"|(?i:\bseeds? [0-9]+(?:, [0-9]+)+)"
        r"|\bp(?:50|99|99\.9) (?:of )?[0-9]"
        r"|(?i:\b(?:stalled|stopped|ended|landed|coasts?)\b[^.;\n]*?\b[0-9]+(?:\.[0-9]+)? ?(?:mm|cm)\b)"
        r"|(?i:\bon franky-sim\b[^.;\n]*?\b[0-9]+/[0-9]+)"),
}


def _files() -> list[Path]:
    out = [p for p in sorted((ROOT / "config").rglob("*")) if p.is_file()]
    for pkg in PACKAGES:
        out += [p for p in sorted((ROOT / pkg).rglob("*"))
                if p.is_file() and p.suffix in SUFFIXES and "__pycache__" not in p.parts]
    out += [ROOT / d for d in REFERENCE_DOCS]
    return out


def findings() -> list[str]:
    """``path:line: what: text`` for every line that holds a date, an issue number or a measured result."""
    out = []
    for path in _files():
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for what, pattern in PATTERNS.items():
                m = pattern.search(line)
                if m:
                    out.append(f"{path.relative_to(ROOT)}:{n}: {what} ({m.group(0)!r}): {line.strip()[:120]}")
    return out


def test_no_results_dates_or_issue_numbers_in_code_configs_and_reference_docs():
    found = findings()
    assert not found, (f"{len(found)} lines hold history (move it to docs/results or docs/measurements.md, or "
                       "link the results page):\n" + "\n".join(found[:60]))


def test_the_check_finds_what_it_is_for():
    assert PATTERNS["a date"].search("run on 2026-12-04")
    assert PATTERNS["an issue number"].search("since issue 30")
    assert PATTERNS["an issue number"].search("(#31)")
    assert PATTERNS["a measured result"].search("windows 13, 15, 10 instead of 22")
    assert PATTERNS["a measured result"].search("measured: 420 episodes without an exception")
    assert not PATTERNS["a measured result"].search("Measure these on the real cell (m)")


if __name__ == "__main__":
    for line in findings():
        print(line)
