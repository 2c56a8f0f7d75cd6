"""Closed-loop re-simulation of a realtime recording (the robot path): each recorded episode's policy,
with each decision's recorded exploration noise, runs again in the simulator from the episode's recorded
start, and the simulated joint positions are compared with the recorded ``joint_states``. ROS-free.

A realtime bag cannot be re-simulated command by command (``nf_bags.resim``): its joint states are
thinned (the Franka driver publishes 100 per s) and its commands answer states that were never recorded.
What it does hold is enough to run the controller again: the policy (``/policy_parameters``, by the
version the episode's rollout names), the noise of every decision (``action - u_mean`` of its
``/rollouts`` chunks), and where the arm was when the episode began (the joint states around its first
sample). The simulated arm is ours (the Panda model of ``sim_bridge``, holding the task's part), with the
joint friction given or identified from the bag (``nf_bags.friction``); what remains between the two is the
difference between the arms, which is what the comparison measures.

``python -m nf_bags.resim_policy BAG [--episodes N] [--friction C V | --friction identify] [--task gear]``
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .reader import joint_trajectory, policies, recorded_task, rollout_chunks, stamp_ns


@dataclass
class PolicyResimResult:
    """How one episode's closed-loop re-simulation compares with its recording."""

    episode_id: int
    policy_version: int
    seconds: float  # simulated, = the recorded episode's length
    states_compared: int  # recorded joint states inside the episode
    max_q_error: float  # rad, over the compared states and the 7 joints
    rms_q_error: float  # rad
    max_tcp_error: float  # m, TCP at the decisions (the rollout's x) against the simulated TCP
    max_tcp_error_at: float  # s into the episode
    final_tcp_error: float  # m, at the episode's last decision
    recorded_success: bool
    simulated_success: bool


class NotCoveredError(ValueError):
    """The recorded joint states do not span the episode (recorded before the first or after the last)."""


def _interpolate(stamps: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    return np.stack([np.interp(at, stamps, values[:, k]) for k in range(values.shape[1])], axis=1)


START_MATCH = 0.005  # m: the joint states at the chunk's stamp put the TCP this close to its first sample
START_GAP = 50e6  # ns: joint states further apart than this around the start cannot give it (a publisher stalled)


def episode_start(chunks: list, rec: object, traj: object, arm: object) -> int:
    """Stamp (ns) of the episode's first sample on the joint states' clock: the first chunk's stamp (its first
    sample, RolloutChunk.msg) when the TCP of the joint states there is within ``START_MATCH`` of that
    sample. Otherwise (a controller that stamped a chunk when it closed it, up to one chunk later) the
    offset, within one chunk's length, at which the joint states' TCP best follows the rollout's x."""
    first = stamp_ns(chunks[0].header) - round(float(rec.t[0]) * 1e9)
    stamps = traj.stamp_ns.astype(np.float64)
    sub = slice(0, min(len(rec.t), 100))
    x = np.asarray(rec.x)[sub]

    def miss(t0: float) -> float:
        at = t0 + np.asarray(rec.t)[sub] * 1e9
        q = _interpolate(stamps, traj.q, at)
        return float(np.abs(np.array([arm.tcp_position(row) for row in q]) - x).max())

    if stamps[0] <= first <= stamps[-1]:
        i = int(np.searchsorted(stamps, first))
        gap = stamps[min(i, len(stamps) - 1)] - stamps[max(i - 1, 0)]
        if gap > START_GAP:
            raise NotCoveredError(f"episode {chunks[0].episode_id}: no joint state recorded for {gap * 1e-6:.0f} ms "
                                  "around its start")
        if miss(first) <= START_MATCH:
            return int(first)
    span = len(chunks[0].t) * float(np.median(np.diff(rec.t))) * 1e9 if len(rec.t) > 1 else 1e9
    offsets = np.arange(-span - 5e6, 5e6, 1e6)  # 1 ms steps back over one chunk
    coarse = min(offsets[::10], key=lambda o: miss(first + o))
    best = min(np.arange(coarse - 1e7, coarse + 1e7, 1e6), key=lambda o: miss(first + o))
    if miss(first + best) > 4 * START_MATCH:
        raise NotCoveredError(f"episode {chunks[0].episode_id}: the joint states never follow its rollout's TCP "
                              f"(closest {1e3 * miss(first + best):.0f} mm; a simulator's reset between two thinned "
                              "states? nf_bags.resim re-simulates a lockstep bag exactly)")
    return int(first + best)


def resimulate_episode(bag: str | Path, chunks: list, traj: object, params_by_version: dict, task: str,
                       friction: tuple[object, object] | None = None,
                       effort_has_gravity: bool = False) -> PolicyResimResult:
    """Re-run one recorded episode (its RolloutChunk messages ``chunks``, in order) in closed loop from the
    joint state at its first sample; ``traj``: the bag's ``joint_trajectory``; ``params_by_version``:
    PolicyParameters messages by version; ``effort_has_gravity``: the recorded effort is the whole applied
    torque (our sim), not a command the robot adds g(q) to (a Franka)."""
    from learner_node.ros_episodes import episode_from_chunks
    from nf_controller_node.arm_model import ArmModel
    from nf_controller_node.controller import FlowController
    from nf_controller_node.flow_eval import FlowEvaluator
    from nf_controller_node.torque_law import TorqueLawConfig
    from nf_core.policy_params import PolicyParameters
    from nf_core.task_spec import held_part_inertia
    from sim_bridge_node.env import InsertionEnv

    env = InsertionEnv(task)
    rec = episode_from_chunks(chunks, success_depth=env.scene.success_depth)
    version = int(chunks[0].policy_version)
    if version not in params_by_version:
        raise ValueError(f"episode {chunks[0].episode_id} ran policy version {version}, which the bag does not hold")
    try:
        params = PolicyParameters.from_msg(params_by_version[version])
    except (AttributeError, ValueError) as exc:  # a bag recorded before the policy carried its law, ...
        raise ValueError(f"episode {chunks[0].episode_id}: its policy (version {version}) cannot be rebuilt from "
                         f"the bag's PolicyParameters: {exc}") from None
    period = float(np.median(np.diff(rec.t))) if len(rec.t) > 1 else 1e-2
    steps = max(int(round(period / 1e-3)), 1)  # 1 ms control steps per decision
    n = len(rec.t)
    stamps = traj.stamp_ns
    arm = ArmModel(part=held_part_inertia(params.law.held_part))
    t0 = episode_start(chunks, rec, traj, arm)
    if stamps[0] > t0 or stamps[-1] < t0 + n * steps * 1_000_000:
        raise NotCoveredError(f"episode {chunks[0].episode_id}: the recorded joint states do not cover it")
    q0 = _interpolate(stamps.astype(np.float64), traj.q, np.array([float(t0)]))[0]
    if friction is not None:
        env.set_joint_friction(*friction)
    env.reset(q=q0)
    ctrl = FlowController(arm, FlowEvaluator(params), TorqueLawConfig().with_policy_law(params.law))
    # the arm got the reset's last command when the episode began: the policy's first commands ramp from it
    # at the rate limit, as on the robot (the recorded effort is the command written; a Franka adds g(q))
    effort0 = _interpolate(stamps.astype(np.float64), traj.effort, np.array([float(t0)]))[0]
    ctrl.reset_rate_limit(effort0 if effort_has_gravity else arm.gravity(q0) + effort0)
    noise = np.asarray(rec.action) - np.asarray(rec.u_mean)
    sim_t, sim_q, sim_x = [], [], []
    for k in range(n):
        for _ in range(steps):
            env.step(ctrl.step(env.q, env.dq, noise[k]))
            sim_t.append(t0 + round((len(sim_t) + 1) * 1e6))
            sim_q.append(env.q.copy())
        sim_x.append(env.x.copy())
    sim_t_arr, sim_q_arr = np.array(sim_t, dtype=np.float64), np.array(sim_q)
    inside = (stamps > t0) & (stamps <= sim_t_arr[-1])
    err = np.abs(_interpolate(sim_t_arr, sim_q_arr, stamps[inside].astype(np.float64)) - traj.q[inside])
    # the rollout's x at decision k is the state that closed it (after its steps): compare like with like
    tcp = np.linalg.norm(np.array(sim_x) - np.asarray(rec.x), axis=1)
    return PolicyResimResult(
        episode_id=int(chunks[0].episode_id), policy_version=version, seconds=n * steps * 1e-3,
        states_compared=int(inside.sum()), max_q_error=float(err.max()) if err.size else float("nan"),
        rms_q_error=float(np.sqrt((err**2).mean())) if err.size else float("nan"),
        max_tcp_error=float(tcp.max()), max_tcp_error_at=float(rec.t[int(np.argmax(tcp))]),
        final_tcp_error=float(tcp[-1]),
        recorded_success=bool(rec.final_success), simulated_success=bool(env.success))


def resimulate_bag(bag: str | Path, episodes: int = 0, task: str | None = None,
                   friction: tuple[object, object] | None = None,
                   skipped: list[str] | None = None) -> list[PolicyResimResult]:
    """Closed-loop re-simulation of the first ``episodes`` complete episodes of ``bag`` (0: all) that its
    joint states cover; why each other episode was left out is appended to ``skipped``."""
    traj = joint_trajectory(bag)
    if len(traj.names) != 7:
        raise ValueError(f"{bag}: the recorded joint states have {len(traj.names)} joints; re-simulation needs "
                         "the 7-joint arm")
    by_version = {int(m.version): m for m in policies(bag)}  # the last message of each version
    from .friction import recorded_drivers

    effort_has_gravity = "no-gravity" not in recorded_drivers(bag)  # a Franka's effort is its command
    results = []
    for chunks in rollout_chunks(bag).values():
        chunks = sorted(chunks, key=lambda c: int(c.seq))
        if not chunks[-1].final or len(chunks) != int(chunks[-1].n_chunks):
            if skipped is not None:
                skipped.append(f"episode {chunks[0].episode_id}: incomplete (a lost chunk or the recording's end)")
            continue
        try:
            results.append(resimulate_episode(bag, chunks, traj, by_version, task or recorded_task(bag) or "gear",
                                              friction, effort_has_gravity))
        except NotCoveredError as exc:  # the recorder started after it or stopped before its end
            if skipped is not None:
                skipped.append(str(exc))
            continue
        if episodes and len(results) >= episodes:
            break
    if not results:
        raise ValueError(f"{bag}: no complete episode (rollout chunks) to re-simulate")
    return results


def main(argv: list[str] | None = None) -> int:
    """Re-simulate a realtime bag's episodes in closed loop and print how far each one's joints went from
    the recording; exit 1 if any episode's largest joint error is above ``--tol`` rad, 2 if the bag
    cannot be re-simulated."""
    from .bagfile import BagError

    ap = argparse.ArgumentParser(prog="python -m nf_bags.resim_policy", description=main.__doc__)
    ap.add_argument("bag")
    ap.add_argument("--episodes", type=int, default=0, help="the first N complete episodes (0: all)")
    ap.add_argument("--task", help="scene (default: from the recorded task_status)")
    ap.add_argument("--friction", nargs="+", metavar="C V",
                    help="the arm's joint friction: Coulomb (Nm) and added viscous (Nm s/rad), for all joints; "
                         "or 'identify' (nf_bags.friction on this bag)")
    ap.add_argument("--tol", type=float, default=float("inf"), help="rad (default: report only)")
    args = ap.parse_args(argv)
    try:
        friction = None
        if args.friction == ["identify"]:
            from .friction import identify_bag

            found = identify_bag(args.bag).sim_parameters()
            friction = (list(map(float, found["joint_friction"])), list(map(float, found["joint_viscous"])))
            print(f"joint friction identified from the bag: Coulomb {np.round(friction[0], 3).tolist()} Nm, "
                  f"added viscous {np.round(friction[1], 3).tolist()} Nm s/rad")
        elif args.friction is not None:
            if len(args.friction) != 2:
                ap.error("--friction takes two numbers (Coulomb Nm, viscous Nm s/rad) or 'identify'")
            friction = (float(args.friction[0]), float(args.friction[1]))
        skipped: list[str] = []
        results = resimulate_bag(args.bag, args.episodes, args.task, friction, skipped)
        for why in skipped:
            print(f"left out: {why}")
    except (BagError, ValueError, KeyError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print("| episode | policy | s | states | max q error (rad) | rms (rad) | max TCP error (mm) at (s) | final (mm) | "
          "inserted: recorded / simulated |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in results:
        print(f"| {r.episode_id} | {r.policy_version} | {r.seconds:.2f} | {r.states_compared} | {r.max_q_error:.4f} | "
              f"{r.rms_q_error:.4f} | {1e3 * r.max_tcp_error:.1f} at {r.max_tcp_error_at:.2f} | "
              f"{1e3 * r.final_tcp_error:.1f} | "
              f"{r.recorded_success} / {r.simulated_success} |")
    worst = max(r.max_q_error for r in results)
    agree = sum(r.recorded_success == r.simulated_success for r in results)
    print(f"{len(results)} episodes: largest joint error {worst:.4f} rad, median of the episodes' largest "
          f"{np.median([r.max_q_error for r in results]):.4f} rad; success agrees in {agree}/{len(results)}")
    return 0 if worst <= args.tol else 1


if __name__ == "__main__":
    raise SystemExit(main())
