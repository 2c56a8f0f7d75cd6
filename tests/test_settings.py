"""The learner's settings are few, grouped, and each one ships: set by a shipped config file or named
in docs/learner.md as a choice a user makes."""

from __future__ import annotations

import ast
import re
from dataclasses import fields
from pathlib import Path

import yaml

from learner_node.config import TrainConfig

ROOT = Path(__file__).resolve().parent.parent
MAX_SETTINGS = 45
MAX_GROUP = 12


def _groups() -> dict[str, list[str]]:
    """The dataclass's ``# --- group ---`` sections and the settings under each, from the source."""
    source = (ROOT / "learner_node" / "learner_node" / "config.py").read_text()
    body = source[source.index("class TrainConfig"):]
    groups: dict[str, list[str]] = {}
    current = None
    for line in body.splitlines():
        head = re.match(r"\s+# --- (\w+) -+", line)
        if head:
            current = head.group(1)
            groups[current] = []
        field = re.match(r"    (\w+): [^=]+ = ", line)
        if field and current:
            groups[current].append(field.group(1))
        if line.startswith("    @property") or line.startswith("    def "):
            break
    return groups


def _shipped_keys() -> set[str]:
    keys: set[str] = set()
    for path in (ROOT / "config").glob("*.yaml"):
        for section in yaml.safe_load(path.read_text()).values():
            keys |= set(section.get("ros__parameters", {}))
    return keys


def test_few_settings_in_small_groups():
    names = [f.name for f in fields(TrainConfig)]
    groups = _groups()
    assert len(names) <= MAX_SETTINGS, f"{len(names)} learner settings (at most {MAX_SETTINGS})"
    assert sorted(n for g in groups.values() for n in g) == sorted(names), "every setting sits in one group"
    assert set(groups) == {"task", "policy", "PPO", "exploration", "run"}
    for name, members in groups.items():
        assert len(members) <= MAX_GROUP, f"group {name}: {len(members)} settings (at most {MAX_GROUP})"


def test_each_setting_is_set_by_a_shipped_config_or_named_as_a_users_choice():
    shipped = _shipped_keys()
    doc = (ROOT / "docs" / "learner.md").read_text()
    choices = set(re.findall(r"`(\w+)`", doc[doc.index("## A user's choices"):]))
    unused = [f.name for f in fields(TrainConfig) if f.name not in shipped and f.name not in choices]
    assert not unused, f"settings no shipped config sets and docs/learner.md does not name as a choice: {unused}"


def test_every_setting_has_a_one_line_meaning():
    tree = ast.parse((ROOT / "learner_node" / "learner_node" / "config.py").read_text())
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "TrainConfig")
    body = cls.body
    for i, node in enumerate(body):
        if isinstance(node, ast.AnnAssign):
            doc = body[i + 1] if i + 1 < len(body) else None
            assert isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant), node.target.id
