"""Joint friction identified from a recorded bag (``python -m nf_bags.friction``) against the MuJoCo
sim's own friction (``joint_friction``, ``joint_viscous``): the ground truth is known.

The sim runs in process (``SimBridge`` on the free scene, as the composed stack steps it) with a
joint-space PD tracking sinusoids on every joint; each state goes into an MCAP bag as the sim node
publishes it (``sensor_msgs/JointState`` serialized by ``SerializedMessage``, effort = the applied
torque, stamps = simulated time), with an episode reset in the middle. No ROS graph, except the
node-parameter test. ``python -m pytest -s tests/test_friction_id.py`` prints the errors.
"""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Collection
from pathlib import Path

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from nf_bags import friction
from nf_bags.writer import BagWriter
from rclpy.serialization import serialize_message
from sensor_msgs.msg import JointState

from nf_core import panda_spec
from nf_core.serialized_message import SerializedMessage
from sim_bridge_node.bridge import BridgeConfig, SimBridge
from sim_bridge_node.env import InsertionEnv, joint_values

from ros_testing import allocate_domain_id, ros_env

Q0 = np.array([0.0, -0.4, 0.0, -2.0, 0.0, 1.8, 0.785])  # rad: TCP high above the table, clear of it throughout
AMPLITUDE = np.array([0.5, 0.35, 0.5, 0.4, 0.6, 0.5, 0.7])  # rad
PERIOD = np.array([3.1, 2.7, 2.3, 3.5, 1.9, 2.2, 1.7])  # s: speeds up to 0.8-2.6 rad/s, every joint both ways
KP = np.array([300.0, 300.0, 300.0, 300.0, 60.0, 60.0, 40.0])  # Nm/rad
KD = np.array([25.0, 25.0, 25.0, 25.0, 4.0, 4.0, 3.0])  # Nm s/rad
COULOMB = np.array([0.8, 0.8, 0.6, 0.6, 0.4, 0.3, 0.2])  # Nm: the truth
VISCOUS = np.array([0.2, 0.2, 0.15, 0.15, 0.05, 0.05, 0.05])  # Nm s/rad on top of panda_spec.JOINT_DAMPING
EPISODE = 4.0  # s of simulated time, twice (a reset between)


def record(bags: dict[Path, int], coulomb: object, viscous: object, amplitude: np.ndarray = AMPLITUDE,
           without_diagnostics: Collection[Path] = (), driver_gravity: bool = False) -> dict[str, int]:
    """Run the sim with this friction and write its joint states into each bag of ``bags`` (path ->
    every how many physics steps a state is recorded: 1 as with ``monitor_period`` 0, 10 as ``make
    run``'s 10 ms), and the sim node's diagnostics status unless the bag is in ``without_diagnostics``.
    ``driver_gravity``: the sim adds gravity itself (``driver_gravity_compensation``), as Franka does."""
    env = InsertionEnv("free")
    env.set_joint_friction(coulomb, viscous)
    bridge = SimBridge(env, BridgeConfig(driver_gravity_compensation=driver_gravity))
    n = len(bridge.joint_names)
    writers = {}
    for path in bags:
        w = BagWriter(path)
        w.add_topic("/joint_states", "sensor_msgs/msg/JointState")
        if path not in without_diagnostics:
            w.add_topic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
            said = KeyValue(key="effort", value="no-gravity" if driver_gravity else "applied")
            status = DiagnosticStatus(name="sim_bridge: driver", hardware_id="mujoco:free", values=[said])
            w.write("/diagnostics", serialize_message(DiagnosticArray(status=[status])), 1)
        writers[path] = w
    state = SerializedMessage(JointState(name=list(bridge.joint_names), position=[0.0] * n, velocity=[0.0] * n,
                                         effort=[0.0] * n), floats=("position", "velocity", "effort"),
                              stamp="header.stamp")

    def publish(step: int) -> None:
        state.set_stamp(bridge.stamp_ns)
        state.floats["position"][:] = env.q
        state.floats["velocity"][:] = env.dq
        state.floats["effort"][:] = bridge.effort  # what the node publishes
        for path, every in bags.items():
            if step % every == 0:
                writers[path].write("/joint_states", bytes(state.payload()), bridge.stamp_ns + 1)

    omega = 2.0 * np.pi / PERIOD
    steps = round(EPISODE / bridge.dt)
    contacts = saturated = 0
    limits = env.torque_limits
    for _ in range(2):
        bridge.reset(q=Q0)  # the reset state: zero velocity and effort
        publish(0)
        for k in range(1, steps + 1):
            t = env.time
            q_ref = Q0 + amplitude * np.sin(omega * t)
            dq_ref = amplitude * omega * np.cos(omega * t)
            gravity = 0.0 if driver_gravity else bridge.gravity()
            assert bridge.step_with(gravity + KP * (q_ref - env.q) + KD * (dq_ref - env.dq))
            contacts += env.data.ncon
            saturated += bool(np.any(np.abs(bridge.torque) >= limits))
            publish(k)
    for w in writers.values():
        w.close()
    return {"contacts": contacts, "saturated": saturated}


def run_tool(*args: str) -> subprocess.CompletedProcess:
    """``python -m <args>`` with the sources importable, as a user runs it."""
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True,
                          env=ros_env(allocate_domain_id()), timeout=120)


def errors(result: dict, coulomb: np.ndarray, viscous: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Identified minus true Coulomb (Nm) and viscous (Nm s/rad, the sim's own damping included) per joint."""
    joints = result["fit"]["joints"]
    fc = np.array([j["coulomb"] for j in joints], dtype=float)
    fv = np.array([j["viscous"] for j in joints], dtype=float)
    return fc - coulomb, fv - (panda_spec.JOINT_DAMPING + viscous)


@pytest.fixture(scope="module")
def friction_bags(tmp_path_factory) -> dict[str, Path]:
    """The sim with known friction, recorded at 1 kHz (with diagnostics) and 100 Hz (without)."""
    tmp = tmp_path_factory.mktemp("friction")
    full, thinned = tmp / "khz", tmp / "hundred_hz"
    facts = record({full: 1, thinned: 10}, COULOMB, VISCOUS, without_diagnostics=[thinned])
    assert facts == {"contacts": 0, "saturated": 0}  # free-space motion, every torque within the limits
    return {"khz": full, "hundred_hz": thinned}


def test_the_command_identifies_the_sims_joint_friction(friction_bags, tmp_path):
    out = tmp_path / "friction.json"
    done = run_tool("nf_bags.friction", str(friction_bags["khz"]), "--json", str(out))
    print(done.stdout)
    assert done.returncode == 0, done.stdout + done.stderr
    result = json.loads(out.read_text())
    fit = result["fit"]
    dc, dv = errors(result, COULOMB, VISCOUS)
    print(f"1 kHz: Coulomb error {np.round(dc, 4).tolist()} Nm, viscous error {np.round(dv, 4).tolist()} Nm s/rad")
    assert np.all(np.abs(dc) <= 0.005), dc  # measured: at most 0.0004 Nm
    assert np.all(np.abs(dv) <= 0.005), dv  # measured: at most 0.0002 Nm s/rad
    # MuJoCo's frictionloss is a soft constraint, short of its full value at low speed on the light wrist:
    # those samples are the outliers the fit leaves out
    assert sum(j["outliers"] for j in fit["joints"]) < 0.01 * sum(j["samples"] for j in fit["joints"])
    assert fit["effort"] == "applied" and "sim_bridge: driver" in fit["effort_source"]
    assert fit["segments"] == 2 and fit["states"] == 2 * (round(EPISODE * 1000) + 1)  # the reset cut the run in two
    assert result["identified"] and not result["warnings"]
    assert result["sim_parameters"]["joint_friction"] == pytest.approx(COULOMB, abs=0.02)
    assert result["sim_parameters"]["joint_viscous"] == pytest.approx(VISCOUS, abs=0.01)
    for name in panda_spec.JOINT_NAMES:
        assert name in done.stdout
    assert "-p sim_bridge:joint_friction:=[0." in done.stdout


def test_at_100_hz_without_diagnostics_the_data_picks_the_effort(friction_bags):
    """``make run`` records joint states every 10 ms; no /diagnostics: the residual decides the effort."""
    result = friction.identify_bag(friction_bags["hundred_hz"])
    assert result.fit.effort == "applied" and result.fit.effort_source.startswith("the data")
    assert result.fit.rate_hz == pytest.approx(100.0)
    dc, dv = errors(result.as_dict(), COULOMB, VISCOUS)
    print(f"\n100 Hz: Coulomb error {np.round(dc, 4).tolist()} Nm, viscous error {np.round(dv, 4).tolist()} Nm s/rad")
    assert np.all(np.abs(dc) <= 0.02), dc  # measured: at most 0.0032 Nm
    assert np.all(np.abs(dv) <= 0.02), dv  # measured: at most 0.0058 Nm s/rad
    forced = friction.identify_bag(friction_bags["hundred_hz"], effort="no-gravity")  # as if a Franka's
    assert forced.fit.effort == "no-gravity" and any("check --effort" in w for w in forced.warnings)


def test_a_sim_that_adds_gravity_itself_reports_the_commands_part(tmp_path):
    """With driver_gravity_compensation the sim's effort leaves its own gravity out (as Franka's driver)
    and its diagnostics say so: the tool takes that convention and still finds the friction."""
    bag = tmp_path / "driver_gravity"
    record({bag: 10}, COULOMB, VISCOUS, driver_gravity=True)
    result = friction.identify_bag(bag)
    assert result.fit.effort == "no-gravity" and "sim_bridge: driver" in result.fit.effort_source
    assert not result.warnings, result.warnings
    dc, dv = errors(result.as_dict(), COULOMB, VISCOUS)
    print(f"\ndriver gravity: Coulomb error {np.round(dc, 4).tolist()} Nm, viscous error {np.round(dv, 4).tolist()}")
    assert np.all(np.abs(dc) <= 0.02), dc
    assert np.all(np.abs(dv) <= 0.02), dv


def test_without_friction_the_sims_own_damping_only(tmp_path):
    bag = tmp_path / "frictionless"
    record({bag: 1}, 0.0, 0.0)
    result = friction.identify_bag(bag)
    dc, dv = errors(result.as_dict(), np.zeros(7), np.zeros(7))
    print(f"\nno friction: Coulomb {np.round(dc, 4).tolist()} Nm, viscous error {np.round(dv, 4).tolist()} Nm s/rad")
    assert np.all(np.abs(dc) <= 0.005), dc  # measured: at most 0.0001 Nm
    assert np.all(np.abs(dv) <= 0.005), dv  # the sim's own damping, panda_spec.JOINT_DAMPING: measured to 0.0001
    for values in result.sim_parameters().values():
        assert values == pytest.approx(np.zeros(7), abs=0.005)


def test_a_joint_that_did_not_move_gets_a_warning_not_a_number(tmp_path, capsys):
    bag = tmp_path / "still_wrist"
    record({bag: 10}, COULOMB, VISCOUS, amplitude=AMPLITUDE * (np.arange(7) < 6))  # joint 7 held still
    code = friction.main([str(bag), "--json", str(tmp_path / "out.json")])
    out = capsys.readouterr().out
    assert code == 1, out
    assert "WARNING: panda_joint7: not identified: moved faster than 0.05 rad/s" in out
    joint7 = json.loads((tmp_path / "out.json").read_text())["fit"]["joints"][6]
    assert joint7["identified"] is False and joint7["coulomb"] is None and joint7["viscous"] is None


def test_a_bag_without_joint_states_is_a_clear_error(tmp_path, capsys):
    bag = tmp_path / "no_states"
    w = BagWriter(bag)
    w.add_topic("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")
    w.write("/diagnostics", serialize_message(DiagnosticArray()), 1)
    w.close()
    for path, words in [(bag, "has no joint states (no /joint_states messages; topics: ['/diagnostics'])"),
                        (tmp_path / "nothing_here", "nothing_here")]:
        assert friction.main([str(path)]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and words in err, err


def test_segments_cut_at_gaps_resets_and_jumps():
    t = np.arange(10) * 0.001
    t[6:] += 0.01  # a 11 ms gap before sample 6
    q = np.zeros((10, 2))
    dq = np.full((10, 2), 0.1)
    effort = np.ones((10, 2))
    dq[3], effort[3] = 0.0, 0.0  # a reset state
    q[8:] += 0.5  # a jump the velocities do not explain
    assert friction.segment_ids(t, q, dq, effort).tolist() == [0, 0, 0, -1, 2, 2, 3, 3, 4, 4]


def test_friction_parameters_are_checked_and_default_to_none():
    env = InsertionEnv("free")
    coulomb, damping = env.joint_friction
    assert np.all(coulomb == 0.0) and np.array_equal(damping, panda_spec.JOINT_DAMPING)
    env.set_joint_friction(0.5, [0.1] * 7)
    coulomb, damping = env.joint_friction
    assert np.all(coulomb == 0.5) and damping == pytest.approx(panda_spec.JOINT_DAMPING + 0.1)
    names = panda_spec.JOINT_NAMES
    assert joint_values([1, 2, 3, 4, 5, 6, 7], names, "x").tolist() == [1, 2, 3, 4, 5, 6, 7]
    for bad, words in [(-0.1, "finite and >= 0"), ([0.1, 0.2], "1 value (every joint) or 7"),
                       (float("nan"), "finite"), ("0.5", "a number or a list"), (True, "a number or a list"),
                       ([0.1] * 6 + [-1.0], "bad: ['panda_joint7']")]:
        with pytest.raises(ValueError, match="joint_viscous") as info:
            env.set_joint_friction(0.0, bad)
        assert words in str(info.value)
    assert np.all(env.joint_friction[0] == 0.5)  # a refused value changed nothing


@pytest.mark.parametrize("args, expect", [
    (["-p", "joint_friction:=0.4", "-p", "joint_viscous:=[0.1, 0.1, 0.1, 0.1, 0.0, 0.0, 0.0]"], None),
    (["-p", "joint_friction:=[0.4, 0.3]"], "joint_friction must have 1 value (every joint) or 7"),
    (["-p", "joint_viscous:=-1"], "joint_viscous must be finite and >= 0"),
])
def test_the_sim_node_takes_a_number_or_a_list_and_refuses_bad_ones(ros_args, args, expect):
    from sim_bridge_node.node import SimBridgeNode

    ros_args(*args)
    if expect is not None:
        with pytest.raises(ValueError, match=expect.replace("(", r"\(").replace(")", r"\)")):
            SimBridgeNode()
        return
    node = SimBridgeNode()
    try:
        coulomb, damping = node.bridge.env.joint_friction
        assert np.all(coulomb == 0.4)
        assert damping == pytest.approx(panda_spec.JOINT_DAMPING + [0.1, 0.1, 0.1, 0.1, 0.0, 0.0, 0.0])
    finally:
        node.destroy_node()

