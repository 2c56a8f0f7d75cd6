"""Closed loop of the flow controller on the simulated Panda (MuJoCo) in free space, at 1 kHz.

Used by the stability tests, possibly in worker processes (everything is built per process).
"""

from __future__ import annotations

import mujoco
import numpy as np

from learner_node.flow import init_flow_weights
from nf_controller_node.arm_model import ArmModel
from nf_controller_node.controller import FlowController
from nf_controller_node.flow_eval import FlowEvaluator
from nf_core.flow_spec import FlowArchitecture
from sim_bridge_node.env import InsertionEnv

ARCH = FlowArchitecture(dim=3, n_flow=2, n_hidden=16, activation="gelu")
STIFFNESS, DAMPING = 40.0, 20.0  # S = 40 I, D = 20 I: near-critical damping, torques stay inside the limits
GOAL_OFFSET = np.array([0.05, 0.0, -0.10])  # m, x_ref relative to the TCP at the mean start pose
V_EVERY = 10  # steps between Lyapunov samples


class PandaLoop:
    """MuJoCo 'free' scene + Pinocchio arm model + flow controller, rebuilt per flow."""

    def __init__(self) -> None:
        self.env = InsertionEnv("free")
        self.arm = ArmModel()
        self.x_ref = self.arm.tcp_position(self.env.q_mean) + GOAL_OFFSET
        self.gear = self.env.model.body(self.env.scene.held_body).id

    def controller(self, seed: int, scale: float) -> FlowController:
        """A controller with random flow weights (seed, init scale)."""
        weights = init_flow_weights(ARCH, np.random.default_rng(seed), scale)
        ev = FlowEvaluator(ARCH, weights, STIFFNESS * np.eye(3), DAMPING * np.eye(3), self.x_ref)
        return FlowController(self.arm, ev)

    def run(self, ctrl: FlowController, start_seed: int, max_steps: int = 30_000,
            force_seed: int | None = None, force_steps: int = 0) -> dict:
        """Run from a sampled start; with force_seed, apply a random force on the gear for force_steps.

        Returns the sampled V trace, the external work, the final distance and the fault, if any.
        """
        env, m, d = self.env, self.env.model, self.env.data
        env.reset(seed=start_seed)
        ctrl.reset_rate_limit()
        ctrl.clear_fault()
        q, dq = d.qpos[:7], d.qvel[:7]
        rng = np.random.default_rng(force_seed) if force_seed is not None else None
        jacp = np.zeros((3, m.nv))
        force = np.zeros(3)
        work = 0.0
        V = [ctrl.lyapunov(q.copy(), dq.copy())]
        works = [0.0]
        nan_torque = False
        saturated = 0
        for n in range(max_steps):
            tau = ctrl.step(q.copy(), dq.copy())
            nan_torque |= not np.all(np.isfinite(tau))
            saturated += ctrl.flags != 0
            d.ctrl[:] = tau
            pushing = rng is not None and n < force_steps
            if pushing:
                if n % 50 == 0:
                    force = rng.normal(0.0, 5.0, 3)  # N, changes every 50 ms
                d.xfrc_applied[self.gear, :3] = force
                mujoco.mj_jacBodyCom(m, d, jacp, None, self.gear)
                v0 = jacp @ d.qvel
            mujoco.mj_step(m, d)
            if pushing:
                mujoco.mj_jacBodyCom(m, d, jacp, None, self.gear)
                work += float(force @ (0.5 * (v0 + jacp @ d.qvel))) * m.opt.timestep
            elif rng is not None and n == force_steps:
                d.xfrc_applied[self.gear] = 0.0
            if (n + 1) % V_EVERY == 0:
                V.append(ctrl.lyapunov(q.copy(), dq.copy()))
                works.append(work)
                if n >= force_steps and np.linalg.norm(self.arm.x - self.x_ref) < 8e-4 \
                        and np.linalg.norm(self.arm.xdot) < 2e-3:
                    break
        return {"V": np.array(V), "work": np.array(works), "steps": n + 1, "fault": ctrl.fault,
                "distance": float(np.linalg.norm(self.arm.x - self.x_ref)), "nan_torque": nan_torque,
                "saturated_steps": saturated}


def run_flow(args: tuple[int, float, list[int]]) -> list[dict]:
    """Worker entry: one flow (seed, scale) over several start seeds; summaries only."""
    seed, scale, starts = args
    loop = _loop()
    ctrl = loop.controller(seed, scale)
    out = []
    for s in starts:
        r = loop.run(ctrl, s)
        V = r["V"]
        out.append({"flow_seed": seed, "scale": scale, "start": s, "distance": r["distance"],
                    "steps": r["steps"], "fault": r["fault"], "nan_torque": r["nan_torque"],
                    "saturated_steps": r["saturated_steps"],
                    "V0": float(V[0]), "max_rise": float(np.max(np.diff(V))) if V.size > 1 else 0.0})
    return out


_LOOP: PandaLoop | None = None


def _loop() -> PandaLoop:
    global _LOOP
    if _LOOP is None:
        _LOOP = PandaLoop()
    return _LOOP
