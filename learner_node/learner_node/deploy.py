"""``deploy_policy``: publish a trained policy to the controller without the learner.

Reads a learner checkpoint (``runs/<run>/checkpoint.pt``, written by ``learner`` or ``train``),
rebuilds its flow policy, sets the goal ``x_ref`` the user measured on the real fixture, and
publishes the parameters on ``/policy_parameters`` latched (reliable, transient local) until
stopped, so a controller started or restarted meanwhile gets them too. The controller validates
them (limits, reach) and installs them between episodes, as it does the learner's.

    deploy_policy runs/gear/checkpoint.pt --x-ref 0.52 0.03 0.11
    deploy_policy runs/gear/checkpoint.pt --keep-x-ref --version 40

The version defaults to the checkpoint's iteration; the controller refuses versions older than
the one it has, so restart it (or pass a larger ``--version``) to go back to an older policy.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

from nf_core.policy_params import PolicyLaw, PolicyParameters


def load_checkpoint_policy(path: str | Path) -> tuple[PolicyParameters, int, float]:
    """(the checkpoint's policy as PolicyParameters, its iteration, its run's ``flow_input_scale``)."""
    import torch  # here, not at the top: --help answers without loading torch

    from .config import TrainConfig
    from .trainer import build_policy

    state = torch.load(Path(path), weights_only=True)
    cfg = TrainConfig(**TrainConfig.with_defaults(state["config"]))
    if cfg.policy != "nf":
        raise ValueError(f"{path}: policy {cfg.policy!r}; the controller runs flow policies (nf) only")
    policy = build_policy(cfg, np.zeros(cfg.dim))
    policy.load_state_dict(state["policy"])
    iteration = int(state["iteration"])
    params = policy.to_params(version=iteration)
    if "law" in state:  # the law it was learned with, as the checkpoint holds it (else its settings')
        params.law = PolicyLaw(**state["law"])
    return params, iteration, cfg.flow_input_scale


def prepare(params: PolicyParameters, x_ref: list[float] | None, version: int | None,
            flow_input_scale: float = 0.0, stiffness_floor: float = 0.0) -> PolicyParameters:
    """``params`` with the user's goal and version, checked like the controller checks them. With the
    run's ``flow_input_scale`` > 0 the flow's landscape moves with the goal (as the learner's
    ``init_checkpoint`` moves it). ``stiffness_floor`` > 0 (N/m): diagonal S entries below it are lifted
    onto it, as ``run_robot --from-checkpoint`` does (``ValueError`` for a non-diagonal S)."""
    if stiffness_floor < 0.0:
        raise ValueError(f"stiffness floor must be >= 0 N/m, got {stiffness_floor}")
    if stiffness_floor > 0.0:
        S = params.stiffness
        if not np.array_equal(S, np.diag(np.diag(S))):
            raise ValueError("a stiffness floor needs a diagonal S (learned gains); this policy's S is full")
        params.stiffness = np.diag(np.maximum(np.diag(S), stiffness_floor))
        params.law = dataclasses.replace(params.law, stiffness_floor=max(params.law.stiffness_floor, stiffness_floor))
    if x_ref is not None:
        from .flow import move_flow_to_goal

        goal = np.asarray(x_ref, dtype=float)
        params.weights = move_flow_to_goal(params.arch, params.weights, params.x_ref, goal, flow_input_scale)
        params.x_ref = goal
    if version is not None:
        params.version = int(version)
    params.validate()
    params.check_limits(reach=True)
    return params


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="deploy_policy", description=__doc__.split("\n\n")[0],
                                 epilog="ROS arguments may follow --ros-args.")
    ap.add_argument("checkpoint", help="learner checkpoint (checkpoint.pt)")
    goal = ap.add_mutually_exclusive_group(required=True)
    goal.add_argument("--x-ref", nargs=3, type=float, metavar=("X", "Y", "Z"),
                      help="goal in the robot's base frame (m), measured on the real fixture")
    goal.add_argument("--keep-x-ref", action="store_true", help="keep the checkpoint's (simulated) goal")
    ap.add_argument("--version", type=int, default=None, help="policy version (default: the checkpoint's iteration)")
    ap.add_argument("--seconds", type=float, default=0.0, help="stop after this long (0: until Ctrl-C)")
    ap.add_argument("--stiffness-floor", type=float, default=0.0, metavar="N_PER_M",
                    help="lift S entries below this (N/m) onto it: a policy from a frictionless simulation may "
                         "have a spring the arm's friction stalls (run_robot --from-checkpoint uses 250 on the FR3; "
                         "default 0: as learned)")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Console script ``deploy_policy``."""
    import rclpy
    from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
    from rclpy.utilities import remove_ros_args

    from nf_core import qos
    from nf_core.topics import POLICY_PARAMETERS

    argv = list(sys.argv if argv is None else argv)
    args = _parser().parse_args(remove_ros_args(argv)[1:])
    params, iteration, scale = load_checkpoint_policy(args.checkpoint)
    try:
        params = prepare(params, None if args.keep_x_ref else args.x_ref, args.version, scale, args.stiffness_floor)
    except ValueError as exc:
        print(f"deploy_policy: {exc}", file=sys.stderr)
        return 2
    rclpy.init(args=argv)
    node = rclpy.create_node("deploy_policy")
    pub = node.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
    pub.publish(params.fill_msg(PolicyParametersMsg()))
    a = params.arch
    node.get_logger().info(f"published {args.checkpoint} (iteration {iteration}) as version {params.version}: "
                           f"n_flow={a.n_flow}, n_hidden={a.n_hidden}, x_ref={params.x_ref.tolist()}, "
                           f"S diagonal {np.round(np.diag(params.stiffness), 1).tolist()} N/m, "
                           f"noise std {np.exp(params.log_std).tolist()} N; its law: force bound "
                           f"{params.law.potential_force_bound:g} N (0: off), held part {params.law.held_part}, "
                           f"stiffness floor {params.law.stiffness_floor:g} N/m; latched until stopped")
    deadline = time.monotonic() + args.seconds if args.seconds > 0 else float("inf")
    try:
        while rclpy.ok() and time.monotonic() < deadline:
            rclpy.spin_once(node, timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
