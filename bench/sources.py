"""Imported first by a bench script: the checkout's package sources come first on ``sys.path``, so a
benchmark measures the working tree (built into ros2_ws or not), as its child processes do."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "nf_bringup"))

from nf_bringup.processes import use_sources

use_sources()
