"""Message definitions for bag schemas, the way rosbag2 writes them: the type's ``.msg`` text
followed by every nested type's text, each once, after a line of 80 ``=`` and ``MSG: pkg/Type``.
Read from the ``.msg`` files each interface package installs under ``share/<pkg>/msg/``
(ament index). ROS-free apart from ``ament_index_python``.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
SEPARATOR = "=" * 80

PRIMITIVES = frozenset({
    "bool", "byte", "char", "float32", "float64", "int8", "uint8", "int16", "uint16", "int32", "uint32",
    "int64", "uint64", "string", "wstring", "time", "duration",
})
_BOUND = re.compile(r"(<=\d+)?(\[[^\]]*\])?$")


def split_type(full: str) -> tuple[str, str]:
    """``pkg/msg/Type`` or ``pkg/Type`` -> (``pkg``, ``Type``)."""
    parts = full.split("/")
    if len(parts) == 3 and parts[1] == "msg":
        return parts[0], parts[2]
    if len(parts) == 2:
        return parts[0], parts[1]
    raise ValueError(f"not a message type name: {full!r}")


def msg_path(package: str, name: str, search: tuple[Path, ...] = ()) -> Path:
    """The installed ``.msg`` file of ``package/name`` (``search`` share dirs first, then the ament index)."""
    for share in search:
        path = Path(share) / package / "msg" / f"{name}.msg"
        if path.exists():
            return path
    from ament_index_python.packages import PackageNotFoundError, get_package_share_directory

    try:
        path = Path(get_package_share_directory(package)) / "msg" / f"{name}.msg"
    except PackageNotFoundError:
        raise LookupError(f"interface package {package!r} not found (is the workspace sourced?)") from None
    if not path.exists():
        raise LookupError(f"no message definition {path}")
    return path


def dependencies(text: str, package: str) -> list[str]:
    """Nested message types (``pkg/Type``) of one ``.msg`` text, in order of appearance."""
    out: list[str] = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        base = _BOUND.sub("", line.split()[0])
        if base in PRIMITIVES:  # constants are always of primitive types
            continue
        if "/" in base:
            dep = "/".join(split_type(base))
        elif base == "Header":
            dep = "std_msgs/Header"
        else:
            dep = f"{package}/{base}"
        if dep not in out:
            out.append(dep)
    return out


@cache
def message_definition(msg_type: str, search: tuple[Path, ...] = ()) -> str:
    """The full rosbag2 schema text of ``msg_type`` (``pkg/msg/Type``), dependencies included."""
    package, name = split_type(msg_type)
    root = msg_path(package, name, search).read_text()
    parts = [root]
    seen = {f"{package}/{name}"}
    queue = dependencies(root, package)
    while queue:
        dep = queue.pop(0)
        if dep in seen:
            continue
        seen.add(dep)
        dep_pkg, dep_name = split_type(dep)
        text = msg_path(dep_pkg, dep_name, search).read_text()
        parts.append(f"{SEPARATOR}\nMSG: {dep}\n{text}")
        queue.extend(d for d in dependencies(text, dep_pkg) if d not in seen)
    return "\n".join(parts)
