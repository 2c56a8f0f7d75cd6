"""``python -m nf_bags.info BAG [--json] [--repair]``: topics, counts, files, chunks of a bag; after a
recorder crash, what is readable and how much was lost (``--repair`` makes such a bag whole for
every rosbag2 reader). No ROS needed."""

from __future__ import annotations

import argparse
import json
import sys

from .bagfile import repair, scan


def main(argv: list[str] | None = None) -> int:
    """Print the report; exit code 0 for a cleanly closed bag, 1 for one whose recorder died."""
    parser = argparse.ArgumentParser(prog="python -m nf_bags.info", description=__doc__.splitlines()[0])
    parser.add_argument("bag", help="bag directory (or one .mcap file)")
    parser.add_argument("--json", action="store_true", help="machine-readable output")
    parser.add_argument("--repair", action="store_true",
                        help="rewrite files without a summary from their readable part and fix metadata.yaml, "
                             "so that every rosbag2 reader opens the bag (reports the state before the repair)")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    result = repair(args.bag) if args.repair else scan(args.bag)
    if args.json:
        window = result.loss_window()
        print(json.dumps({
            "closed": result.closed, "counts": dict(result.counts), "metadata_counts": result.metadata_counts,
            "lost": result.lost, "lost_seconds_known": window[0] if window else 0.0,
            "lost_seconds_more_at_most": window[1] if window else 0.0,
            "files": [{"path": str(f.path), "complete": f.complete, "chunks": f.chunks, "size": f.size,
                       "torn_bytes": f.torn_bytes, "messages": sum(f.counts.values())} for f in result.files],
        }, indent=1))
    else:
        print(result.report())
    return 0 if result.closed else 1


if __name__ == "__main__":
    raise SystemExit(main())
