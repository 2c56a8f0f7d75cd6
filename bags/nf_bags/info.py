"""``python -m nf_bags.info BAG [--json] [--repair [--output DIR]]``: topics, counts, files, chunks of a
bag, and the arms whose topics it holds (namespaces, ``/`` for an arm without one);
after a recorder crash or damage, what is readable, what was skipped and how much was lost
(``--repair`` writes a repaired copy that every rosbag2 reader opens; the original is never
changed). No ROS needed.

Exit codes: 0 closed cleanly (or ``--repair`` wrote a verified copy, or had nothing to repair),
1 not closed (recorder died) or damaged, 2 not readable as a bag (missing path, sqlite3 bag,
invalid metadata.yaml, a file it lists is missing) or the repair failed.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from .bagfile import BagError, BagScan, repair, scan
from .resim import resimulable
from .topics import arm_of, arms_of


def as_json(result: BagScan) -> dict[str, Any]:
    """The scan as plain data (``--json``)."""
    window = result.loss_window()
    return {
        "state": result.state, "closed": result.closed, "counts": dict(result.counts),
        "arms": arms_of(result.counts),
        "metadata_counts": result.metadata_counts, "lost": result.lost,
        "lost_seconds_known": window[0] if window else 0.0, "loss_bound": result.loss_bound(),
        "damage": result.problems(),
        "files": [{"path": str(f.path), "complete": f.complete, "damaged": f.damaged, "chunks": f.chunks,
                   "size": f.size, "torn_bytes": f.torn, "messages": f.messages,
                   "summary_messages": f.summary_messages,
                   "damage": [{"offset": d.offset, "length": d.length, "what": d.what,
                               "messages_lost": d.messages_lost, "suspect_messages": d.suspect_messages}
                              for d in f.damage]} for f in result.files],
    }


def arms_line(result: BagScan) -> str:
    """One line naming the arms in the bag with their topics' and messages' counts."""
    found = arms_of(result.counts)
    if not found:
        return "arms: none (no arm topics)"
    parts = []
    for arm in found:
        topics = [t for t in result.counts if arm_of(t) == arm]
        parts.append(f"{arm} ({len(topics)} topics, {sum(result.counts[t] for t in topics)} messages)")
    return f"arms: {len(found)}: " + ", ".join(parts)


def main(argv: list[str] | None = None) -> int:
    """Print the report; exit code as in the module docstring."""
    parser = argparse.ArgumentParser(prog="python -m nf_bags.info", description=__doc__.splitlines()[0],
                                     epilog="exit codes: 0 closed cleanly (or repaired copy written), 1 not closed "
                                            "or damaged, 2 not a readable bag or repair failed")
    parser.add_argument("bag", help="bag directory (or one .mcap file)")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    parser.add_argument("--repair", action="store_true",
                        help="write a repaired copy (<bag>.repaired, or <name>.repaired.mcap) holding every readable "
                             "message, each file whole with its summary, and a fixed metadata.yaml; the original "
                             "is left as it is. Reports the original and what the copy dropped")
    parser.add_argument("--output", help="with --repair: where to write the copy (must not exist)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    if args.output and not args.repair:
        parser.error("--output needs --repair")
    try:
        if args.repair:
            fixed = repair(args.bag, args.output)
            result = fixed.before
        else:
            fixed = None
            result = scan(args.bag)
    except BagError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc.strerror or exc}: {exc.filename or args.bag}", file=sys.stderr)
        return 2
    if args.json:
        out = as_json(result)
        if fixed is not None:
            out["repair"] = {"output": str(fixed.output) if fixed.output else None, "messages": fixed.messages,
                             "dropped": fixed.dropped}
        if result.closed:
            out["resimulable"], out["resimulable_why"] = resimulable(args.bag)
        print(json.dumps(out, indent=1))
    else:
        print(result.report())
        print(arms_line(result))
        if result.closed:
            ok, why = resimulable(args.bag)
            print(f"re-simulable (nf_bags.resim): {'yes' if ok else 'no'}: {why}")
        if fixed is not None:
            print(fixed.report())
    if fixed is not None:
        return 0
    return 0 if result.closed or result.state == "repaired" else 1


if __name__ == "__main__":
    raise SystemExit(main())
