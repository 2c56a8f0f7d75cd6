"""A ROS message serialized once and then rewritten in place, for messages a driver thread publishes
at a high rate with the same layout every time (joint states, applied commands, clock, task status).

Publishing a typed message from Python runs the message's field setters and rclpy's conversion to
C on every call; inside the composed stack's lockstep loop that cost the driver thread about as much
as the controller's tick (``bench/bench_stack.py``). Here the message is serialized once (CDR), the
byte offsets of its fixed-size fields are found by serializing sentinel values, and each publish
writes the new values into the buffer through numpy views and hands rclpy the bytes
(``Publisher.publish`` takes serialized messages as ``bytes``). Only fields whose size never
changes can be rewritten: float64 arrays of a fixed length, float64 scalars, bools, a
``builtin_interfaces/Time`` stamp and strings of a fixed length.

    state = JointState(name=names, position=[0.0] * 7, velocity=[0.0] * 7, effort=[0.0] * 7)
    raw = SerializedMessage(state, floats=("position", "velocity", "effort"), stamp="header.stamp")
    raw.floats["position"][:] = q
    raw.set_stamp(stamp_ns)
    publisher.publish(raw.payload())
"""

from __future__ import annotations

import copy
from collections.abc import Sequence
from typing import Any

import numpy as np
from rclpy.serialization import serialize_message

_SEC, _NANOSEC = 0x5A3C_1E27, 0x2B4D_6F13  # sentinel stamp (int32 sec, uint32 nanosec)


def _get(msg: Any, path: str) -> Any:
    for part in path.split("."):
        msg = msg[int(part)] if part.isdigit() else getattr(msg, part)
    return msg


def _set(msg: Any, path: str, value: Any) -> None:
    head, _, last = path.rpartition(".")
    owner = _get(msg, head) if head else msg
    if last.isdigit():
        owner[int(last)] = value
    else:
        setattr(owner, last, value)


def _locate_bool(probe: Any, name: str, tries: int = 4) -> int:
    """Offset of bool field ``name`` (False in ``probe``) in its serialized message: the one byte that is
    0 with False and 1 with True in every one of ``tries`` serializations each way. CDR's alignment
    padding is not initialised by the serializer (it has differed between two serializations of the
    same message), so a plain diff of one pair can show more than the bool."""
    zeros, ones = [], []
    for _ in range(tries):
        zeros.append(np.frombuffer(serialize_message(probe), np.uint8))
        _set(probe, name, True)
        ones.append(np.frombuffer(serialize_message(probe), np.uint8))
        _set(probe, name, False)
    found = np.flatnonzero(np.all(np.stack(zeros) == 0, axis=0) & np.all(np.stack(ones) == 1, axis=0))
    if found.size != 1:
        raise ValueError(f"cannot locate bool field {name} in the serialized message")
    return int(found[0])


def _find_once(data: bytes, pattern: bytes, what: str) -> int:
    at = data.find(pattern)
    if at < 0 or data.find(pattern, at + 1) >= 0:
        raise ValueError(f"cannot locate {what} in the serialized message (not found or not unique)")
    return at


class SerializedMessage:
    """``msg`` serialized once; ``floats[name]`` are float64 views of the named fields in the buffer
    (their lengths as in ``msg``), ``set_stamp``, ``set_bool`` and ``set_text`` rewrite the others.
    Field names are dotted paths (``header.stamp``, ``layout.dim.0.label``)."""

    def __init__(self, msg: Any, floats: Sequence[str] = (), stamp: str | None = None,
                 bools: Sequence[str] = (), texts: Sequence[str] = ()) -> None:
        probe = copy.deepcopy(msg)
        sentinels: dict[str, np.ndarray] = {}
        rng = np.random.default_rng(20261202)
        for name in floats:
            value = _get(probe, name)
            n = 1 if isinstance(value, float) else len(value)
            sentinels[name] = 1e3 + rng.random(n)  # distinct, and unlike anything else in the message
            _set(probe, name, float(sentinels[name][0]) if isinstance(value, float) else sentinels[name].tolist())
        text_sentinels = {}
        for i, name in enumerate(texts):
            n = len(_get(probe, name))
            text_sentinels[name] = (f"\x01{i:02d}" + "\x02" * n)[:n]
            if n < 3:
                raise ValueError(f"text field {name} needs at least 3 characters to be located")
            _set(probe, name, text_sentinels[name])
        if stamp is not None:
            t = _get(probe, stamp)
            t.sec, t.nanosec = _SEC, _NANOSEC
        for name in bools:
            _set(probe, name, False)
        data = serialize_message(probe)
        if data[:2] != b"\x00\x01":
            raise ValueError("only little-endian CDR messages can be rewritten in place")
        self._buf = bytearray(data)
        self.floats: dict[str, np.ndarray] = {}
        for name, values in sentinels.items():
            at = _find_once(data, values.astype("<f8").tobytes(), f"float64 field {name}")
            self.floats[name] = np.frombuffer(self._buf, dtype="<f8", count=values.size, offset=at)
        self._texts = {name: (_find_once(data, s.encode(), f"text field {name}"), len(s))
                       for name, s in text_sentinels.items()}
        self._stamp = None
        if stamp is not None:
            at = _find_once(data, np.array([_SEC], "<i4").tobytes() + np.array([_NANOSEC], "<u4").tobytes(),
                            f"stamp {stamp}")
            self._stamp = (np.frombuffer(self._buf, "<i4", 1, at), np.frombuffer(self._buf, "<u4", 1, at + 4))
        self._bools = {}
        for name in bools:
            self._bools[name] = _locate_bool(probe, name)
        # the rest of the message as given, not the sentinels
        for name in floats:
            self.floats[name][:] = np.atleast_1d(np.asarray(_get(msg, name), dtype=np.float64))
        for name in texts:
            self.set_text(name, _get(msg, name))
        if stamp is not None:
            t = _get(msg, stamp)
            self.set_stamp(t.sec * 1_000_000_000 + t.nanosec)
        for name in bools:
            self.set_bool(name, _get(msg, name))

    def set_stamp(self, stamp_ns: int) -> None:
        """The stamp field, from nanoseconds."""
        sec, nanosec = divmod(int(stamp_ns), 1_000_000_000)
        self._stamp[0][0], self._stamp[1][0] = sec, nanosec

    def set_bool(self, name: str, value: bool) -> None:
        """A bool field."""
        self._buf[self._bools[name]] = 1 if value else 0

    def set_text(self, name: str, text: str) -> None:
        """A text field; ``ValueError`` unless ``text`` has the length it was built with (ASCII)."""
        at, n = self._texts[name]
        data = text.encode("ascii")
        if len(data) != n:
            raise ValueError(f"text field {name} holds {n} characters, got {len(data)}: {text!r}")
        self._buf[at:at + n] = data

    def payload(self) -> bytes:
        """The serialized message as it stands (a copy, for ``Publisher.publish``)."""
        return bytes(self._buf)
