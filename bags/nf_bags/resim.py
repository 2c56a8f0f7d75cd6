"""Deterministic re-simulation of a lockstep recording: a fresh ``SimBridge`` starts from a recorded
reset state (its joint positions; a reset state has zero velocity) and is stepped with the recorded
commands, each applied to the state whose stamp its label names, as the lockstep sim did. The
states it produces are compared with the recorded ``joint_states``. ROS-free.

The recorded arm's joint friction is not in the bag: give it (``friction``: Coulomb and added viscous
per joint, as ``sim_bridge``'s ``joint_friction`` / ``joint_viscous``), or take what ``nf_bags.friction``
identifies from the bag's own states and efforts (``--friction identify``).

``python -m nf_bags.resim BAG [--episode N | --start-ns S] [--task gear] [--friction C V | --friction identify]``
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .reader import commands_by_state, joint_trajectory, recorded_task


@dataclass
class ResimResult:
    """How a re-simulation compares with the recording."""

    start_ns: int  # stamp of the recorded reset state it started from
    steps: int  # commands applied
    max_q_error: float  # rad, max over steps and joints
    max_dq_error: float  # rad/s
    max_effort_error: float  # Nm (torque applied in the step, as joint_states.effort reports it)
    stop_reason: str

    @property
    def max_error(self) -> float:
        """Largest of the position and velocity errors."""
        return max(self.max_q_error, self.max_dq_error)


def episode_starts(bag: str | Path) -> list[int]:
    """Stamps (ns) of the recorded reset states: the start of the run and of every episode."""
    traj = joint_trajectory(bag)
    return [int(traj.stamp_ns[i]) for i in traj.resets()]


def resimulate(bag: str | Path, start_ns: int | None = None, task: str | None = None,
               driver_gravity_compensation: bool = False, max_steps: int | None = None,
               friction: tuple[object, object] | None = None) -> ResimResult:
    """Re-run the recorded commands from the reset state at ``start_ns`` (default: the first one)
    until the next reset state, the last answered state, or ``max_steps``; with ``friction`` (Coulomb
    Nm, added viscous Nm s/rad: a number or one per joint each) the simulated arm has that joint friction."""
    from sim_bridge_node.bridge import ACCEPTED, BridgeConfig, SimBridge
    from sim_bridge_node.env import InsertionEnv

    traj = joint_trajectory(bag)
    commands, _ = commands_by_state(bag)
    resets = [int(traj.stamp_ns[i]) for i in traj.resets()]
    if not resets:
        raise ValueError("the bag has no reset state (zero velocity and effort) to start from")
    start_ns = resets[0] if start_ns is None else int(start_ns)
    if start_ns not in resets:
        raise ValueError(f"no recorded reset state at {start_ns} ns; reset states: {resets[:10]}"
                         f"{'...' if len(resets) > 10 else ''}")
    end_ns = next((r for r in resets if r > start_ns), None)
    index = {int(s): i for i, s in enumerate(traj.stamp_ns)}
    i = index[start_ns]
    if len(traj.names) != 7 or traj.q.shape[1] != 7:
        raise ValueError(f"the recorded joint states have {len(traj.names)} joints; re-simulation needs the "
                         "7-joint arm")
    env = InsertionEnv(task or recorded_task(bag) or "gear")
    if friction is not None:
        env.set_joint_friction(*friction)
    bridge = SimBridge(env, BridgeConfig(mode="lockstep", driver_gravity_compensation=driver_gravity_compensation))
    bridge.reset(q=traj.q[i])
    step_ns = round(bridge.dt * 1e9)  # consecutive recorded states are one physics step apart
    errors = np.zeros(3)
    steps = 0
    reason = "end of the recording"
    while True:
        stamp = int(traj.stamp_ns[i])
        if max_steps is not None and steps >= max_steps:
            reason = "max_steps"
            break
        if stamp not in commands:
            reason = "a state without a command (the controller paused or stopped)"
            break
        if i + 1 >= len(traj.stamp_ns):
            break
        if end_ns is not None and int(traj.stamp_ns[i + 1]) >= end_ns:
            reason = "the next reset"
            break
        gap = int(traj.stamp_ns[i + 1]) - stamp
        if gap != step_ns:
            reason = (f"a {gap} ns gap to the next recorded state, not one {step_ns} ns step (the composed "
                      f"sim_bridge's monitor_period thins joint_states and commands; re-simulation needs "
                      f"every step: record with monitor_period 0)")
            break
        if bridge.accept_command(commands[stamp], 0.0) != ACCEPTED:
            raise ValueError(f"the recorded command for {stamp} ns is not valid: {bridge.last_error}")
        bridge.step_commanded()
        steps += 1
        i += 1
        env = bridge.env
        errors = np.maximum(errors, [np.abs(env.q - traj.q[i]).max(), np.abs(env.dq - traj.dq[i]).max(),
                                     np.abs(bridge.torque - traj.effort[i]).max()])
    return ResimResult(start_ns, steps, float(errors[0]), float(errors[1]), float(errors[2]), reason)


def resimulable(bag: str | Path) -> tuple[bool, str]:
    """Whether ``bag`` can be re-simulated: in every episode that has lockstep commands (from its reset
    state to its last answered state), a joint state every physics step (1 ms) and the command that
    answered each. (yes/no, why)."""
    from .bagfile import BagError

    try:
        traj = joint_trajectory(bag)
        commands, _ = commands_by_state(bag)
    except (BagError, KeyError, ValueError) as exc:
        return False, f"no joint states and commands to re-simulate ({exc})"
    stamps = traj.stamp_ns.astype(np.int64)
    thinned = ("joint states every {} ms, not every 1 ms step: record the sim and the controller as two "
               "processes (make run ARGS=\"--separate\"), whose sim publishes every step")
    if stamps.size > 1 and np.median(np.diff(stamps)) > 1_000_000:
        return False, thinned.format(f"{np.median(np.diff(stamps)) / 1e6:g}")
    resets = [int(i) for i in traj.resets()]
    if not resets:
        return False, "no reset state (a joint state with zero velocity and effort) to start from"
    episodes, steps = 0, 0
    for first, end in zip(resets, [*resets[1:], len(stamps)], strict=True):
        answered = [i for i in range(first, end) if int(stamps[i]) in commands]
        if not answered:
            continue
        gaps = np.diff(stamps[first:answered[-1] + 2][: answered[-1] + 2 - first])
        if np.any(gaps != 1_000_000):
            return False, thinned.format(f"{np.max(gaps) / 1e6:g}")
        episodes, steps = episodes + 1, steps + len(answered)
    if not episodes:
        return False, "no lockstep commands (state_stamp_ns labels): a realtime recording cannot be re-simulated"
    return True, f"every 1 ms state and its command in {episodes} episode(s), {steps} steps"


def start_of_episode(bag: str | Path, episode: int) -> int:
    """Stamp (ns) of the reset state that starts ``episode`` (0: the first reset state in the bag);
    ``ValueError`` naming how many there are if it does not exist."""
    starts = episode_starts(bag)
    if not starts:
        raise ValueError(f"{bag} has no reset state (a joint state with zero velocity and effort on "
                         f"/joint_states): it cannot be re-simulated")
    if not 0 <= episode < len(starts):
        raise ValueError(f"episode {episode} does not exist: {bag} has {len(starts)} reset states "
                         f"(--episode 0..{len(starts) - 1})")
    return starts[episode]


def main(argv: list[str] | None = None) -> int:
    """Re-simulate one recorded episode and print the largest deviation; exit 1 above ``--tol``,
    2 if the bag cannot be re-simulated (no such episode or reset state, no lockstep commands)."""
    from .bagfile import BagError

    parser = argparse.ArgumentParser(prog="python -m nf_bags.resim", description=main.__doc__)
    parser.add_argument("bag")
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--episode", type=int, default=0, help="index of the reset state to start from (0: first)")
    group.add_argument("--start-ns", type=int, help="stamp of the reset state to start from")
    parser.add_argument("--task", help="scene (default: from the recorded task_status)")
    parser.add_argument("--driver-gravity-compensation", action="store_true")
    parser.add_argument("--friction", nargs="+", metavar="C V",
                        help="the arm's joint friction: Coulomb (Nm) and added viscous (Nm s/rad), for all joints; "
                             "or 'identify' (nf_bags.friction on this bag)")
    parser.add_argument("--tol", type=float, default=1e-9)
    args = parser.parse_args(argv)
    try:
        start = args.start_ns if args.start_ns is not None else start_of_episode(args.bag, args.episode)
        friction = None
        if args.friction == ["identify"]:
            from .friction import identify_bag

            found = identify_bag(args.bag)
            p = {k: [round(float(v), 4) for v in values] for k, values in found.sim_parameters().items()}
            friction = (p["joint_friction"], p["joint_viscous"])
            print(f"joint friction identified from the bag: Coulomb {p['joint_friction']} Nm, added viscous "
                  f"{p['joint_viscous']} Nm s/rad")
            missing = [j.name for j in found.joints if not j.identified]
            if missing:
                print(f"warning: not identified (too little motion), re-simulated without friction: {missing}")
        elif args.friction is not None:
            if len(args.friction) != 2:
                parser.error("--friction takes two numbers (Coulomb Nm, viscous Nm s/rad) or 'identify'")
            friction = (float(args.friction[0]), float(args.friction[1]))
        r = resimulate(args.bag, start, args.task, args.driver_gravity_compensation, friction=friction)
    except (BagError, ValueError, KeyError, IndexError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if r.steps == 0:
        print(f"error: nothing to re-simulate from {r.start_ns} ns: {r.stop_reason} (lockstep commands carry "
              f"state_stamp_ns=<stamp> labels; a realtime recording has none)", file=sys.stderr)
        return 2
    print(f"re-simulated {r.steps} steps from {r.start_ns} ns (stopped at {r.stop_reason}): "
          f"max |q error| {r.max_q_error:.3g} rad, |dq error| {r.max_dq_error:.3g} rad/s, "
          f"|torque error| {r.max_effort_error:.3g} Nm")
    return 0 if r.max_error <= args.tol else 1


if __name__ == "__main__":
    raise SystemExit(main())
