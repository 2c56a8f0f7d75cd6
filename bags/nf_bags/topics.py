"""The topic names of an arm stack as recorded, and which arm (namespace) a recorded topic belongs to:
a bag of many arms (``run_stack --arms N``) holds each arm's topics under its namespace
(``/arm0/rollouts``). Plain string handling, cheap to import (``nf_bags.info`` uses it)."""

from __future__ import annotations

from collections.abc import Iterable

JOINT_STATES = "/joint_states"
COMMANDS = "/effort_controller/commands"
TASK_STATUS = "/task_status"
CONTROLLER_STATUS = "/controller_status"
ROLLOUTS = "/rollouts"
POLICY = "/policy_parameters"
# the topics an arm stack publishes (relative names under its namespace): how an arm is recognised
ARM_TOPICS = (JOINT_STATES, COMMANDS, TASK_STATUS, CONTROLLER_STATUS, ROLLOUTS, POLICY)


def arm_of(topic: str) -> str | None:
    """The namespace of the arm that ``topic`` belongs to ("/" for an arm without one), None for a
    topic that is not an arm topic."""
    for suffix in ARM_TOPICS:
        if topic.endswith(suffix):
            ns = topic[: -len(suffix)]
            if ns == "" or ns.startswith("/"):
                return ns or "/"
    return None


def arm_topic(arm: str, topic: str) -> str:
    """The absolute name of ``topic`` (one of ``ARM_TOPICS``) of ``arm`` ("/" or "/arm0")."""
    return topic if arm in ("", "/") else arm.rstrip("/") + topic


def arms_of(topics: Iterable[str]) -> list[str]:
    """The arm namespaces among ``topics`` (names), sorted ("/" for an arm without a namespace)."""
    return sorted({a for a in map(arm_of, topics) if a is not None})
