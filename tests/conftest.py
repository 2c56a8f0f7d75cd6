"""Shared pytest setup: every ROS context in the test process stays on loopback, over UDP."""

import os

from nf_bringup.processes import isolate

isolate(os.environ, domain_id=None, sources=False)
