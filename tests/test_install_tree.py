"""The colcon install tree has what `ros2 run` and the ament index need."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from ros_testing import REPO, allocate_domain_id, ros_env

INSTALL = REPO / "ros2_ws" / "install"
# every ament_python package linked in the workspace (a new one is covered by these tests at once)
PYTHON_PACKAGES = tuple(sorted(p.name for p in (REPO / "ros2_ws" / "src").iterdir() if (p / "setup.py").is_file()))
# the ones with executables (nf_core and franka_driver are libraries: nf_bringup composes the driver)
NODE_PACKAGES = tuple(p for p in PYTHON_PACKAGES
                      if '"console_scripts"' in (REPO / "ros2_ws" / "src" / p / "setup.py").read_text())


def _console_scripts(pkg: str) -> list[str]:
    text = (REPO / pkg / "setup.py").read_text()
    block = text.split('"console_scripts": [')[1].split("]")[0]
    return [line.split("=")[0].strip().strip('"') for line in block.splitlines() if "=" in line]


@pytest.mark.parametrize("pkg", [*PYTHON_PACKAGES, "nf_msgs"])
def test_ament_index_marker(pkg):
    assert (INSTALL / pkg / "share" / "ament_index" / "resource_index" / "packages" / pkg).is_file()
    assert (INSTALL / pkg / "share" / pkg / "package.xml").is_file()


def test_interfaces_are_indexed():
    index = INSTALL / "nf_msgs" / "share" / "ament_index" / "resource_index" / "rosidl_interfaces" / "nf_msgs"
    listed = set(index.read_text().split())
    for name in ("msg/PolicyParameters.msg", "msg/RolloutChunk.msg", "msg/ControllerStatus.msg",
                 "msg/TaskStatus.msg", "srv/ResetSim.srv", "action/RunEpisode.action"):
        assert name in listed, f"{name} missing from {index}"


def test_only_the_core_and_the_franka_driver_are_libraries():
    assert set(PYTHON_PACKAGES) - set(NODE_PACKAGES) == {"nf_core", "franka_driver"}


@pytest.mark.parametrize("pkg", NODE_PACKAGES)
def test_executables_in_lib_pkg_and_runnable(pkg):
    scripts = _console_scripts(pkg)
    assert scripts, f"{pkg} declares no console scripts"
    runs = {}
    for exe in scripts:  # all at once: each one imports its package (torch for the learner's) first
        path = INSTALL / pkg / "lib" / pkg / exe
        assert path.is_file() and os.access(path, os.X_OK), f"{path} missing or not executable"
        runs[exe] = subprocess.Popen([str(path), "--help"], env=ros_env(allocate_domain_id()),
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for exe, proc in runs.items():
        out, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, f"{exe} --help failed:\n{err[-2000:]}"
        assert "usage" in out.lower(), exe


def test_src_holds_relative_symlinks():
    src = REPO / "ros2_ws" / "src"
    for link in src.iterdir():
        assert link.is_symlink() and not os.readlink(link).startswith("/"), link
        assert (link / "package.xml").is_file(), link
    assert {p.name for p in src.iterdir()} == {*PYTHON_PACKAGES, "nf_msgs", "tf2_msgs"}


def test_launch_files_are_installed_and_parse():
    import ast

    launch = INSTALL / "nf_bringup" / "share" / "nf_bringup" / "launch"
    files = sorted(launch.glob("*.launch.py"))
    assert {f.name for f in files} >= {"gear_learning.launch.py", "controller_hardware.launch.py"}
    for f in files:  # the launch package itself exists only on full ROS 2 installs: check the syntax here
        assert "generate_launch_description" in {n.name for n in ast.parse(f.read_text()).body
                                                 if isinstance(n, ast.FunctionDef)}


def test_env_file_sets_loopback_discovery():
    text = Path(REPO / "env.sh").read_text()
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST" in text
    assert "install/setup.bash" in text


def test_env_file_puts_console_scripts_and_bags_on_the_path():
    """The README's commands (train, nf_report, render_scene, python -m nf_bags.*) work in a shell
    that sourced env.sh and nothing else."""
    script = f"source {REPO / 'env.sh'} && command -v train nf_report nf_compare run_stack render_scene " \
             "deploy_policy && python -c 'import nf_bags.record'"
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = "/usr/bin:/bin"
    done = subprocess.run(["bash", "-c", script], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert len(done.stdout.split()) == 6
