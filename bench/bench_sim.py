"""Physics throughput of the gear scene during insertion: single env, batched threads, mujoco.rollout.

The measured state is the gear seated on the shaft while the arm pushes down (16 gear-shoulder
contacts, the heaviest contact phase), plus a contact-free reference. Every figure is the median
over repeats of steps per second. Writes ``bench/results/sim.json`` and prints it.

    python bench/bench_sim.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import mujoco
import numpy as np
import sources  # noqa: F401  (the package sources first on sys.path)

from sim_bridge_node.batched_env import BatchedEnv
from sim_bridge_node.env import InsertionEnv
from sim_bridge_node.scripted_insertion import push_torque, run_insertion

ROOT = Path(__file__).resolve().parents[1]

STATE_SPEC = mujoco.mjtState.mjSTATE_FULLPHYSICS


def seated_state(env: InsertionEnv) -> tuple[np.ndarray, np.ndarray]:
    """Drive the gear onto the shaft; return the full physics state and a pushing torque."""
    env.reset()
    result = run_insertion(env, seconds=3.2, push_depth=0.01)
    if not result["success"]:
        raise RuntimeError("benchmark setup failed: the gear did not seat")
    state = np.zeros(mujoco.mj_stateSize(env.model, STATE_SPEC))
    mujoco.mj_getState(env.model, env.data, state, STATE_SPEC)
    return state, push_torque(env, env.goal_position - [0.0, 0.0, 0.01])


def _load(env: InsertionEnv, state: np.ndarray) -> None:
    mujoco.mj_setState(env.model, env.data, state, STATE_SPEC)
    mujoco.mj_forward(env.model, env.data)


def bench_single(env: InsertionEnv, state: np.ndarray, tau: np.ndarray, steps: int, repeats: int) -> dict:
    """env.step and bare mj_step rates on one thread."""
    rates, raw = [], []
    for _ in range(repeats):
        _load(env, state)
        t0 = time.perf_counter()
        for _ in range(steps):
            env.step(tau)
        rates.append(steps / (time.perf_counter() - t0))
        _load(env, state)
        env.data.ctrl[:] = tau
        t0 = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(env.model, env.data)
        raw.append(steps / (time.perf_counter() - t0))
    return {
        "env_step_per_s": statistics.median(rates),
        "mj_step_per_s": statistics.median(raw),
        "contacts": int(env.data.ncon),
    }


def bench_batched(n_envs: int, n_threads: int, state: np.ndarray, tau: np.ndarray, steps: int,
                  repeats: int) -> dict:
    """BatchedEnv.step rate in environment-steps per second."""
    with BatchedEnv("gear", n_envs=n_envs, n_threads=n_threads) as batch:
        taus = np.tile(tau, (n_envs, 1))
        rates = []
        for _ in range(repeats):
            for env in batch.envs:
                _load(env, state)
            t0 = time.perf_counter()
            for _ in range(steps):
                batch.step(taus)
            rates.append(n_envs * steps / (time.perf_counter() - t0))
        contacts = int(np.median([e.data.ncon for e in batch.envs]))
    return {"n_envs": n_envs, "n_threads": n_threads, "env_steps_per_s": statistics.median(rates),
            "contacts": contacts}


def bench_rollout(model: mujoco.MjModel, n_envs: int, n_threads: int, state: np.ndarray, tau: np.ndarray,
                  steps: int, repeats: int) -> dict:
    """mujoco.rollout driven one step per call (closed loop), state fed back every step."""
    from mujoco import rollout

    datas = [mujoco.MjData(model) for _ in range(n_threads)]
    control = np.tile(tau, (n_envs, 1, 1))
    rates = []
    with rollout.Rollout(nthread=n_threads) as runner:
        for _ in range(repeats):
            states = np.tile(state, (n_envs, 1))
            t0 = time.perf_counter()
            for _ in range(steps):
                out, _ = runner.rollout(model, datas, states, control, nstep=1)
                states = out[:, 0, :]
            rates.append(n_envs * steps / (time.perf_counter() - t0))
    return {"n_envs": n_envs, "n_threads": n_threads, "env_steps_per_s": statistics.median(rates)}


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark, write bench/results/sim.json, print and return the results."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer steps and repeats")
    parser.add_argument("--out", default=str(ROOT / "bench" / "results" / "sim.json"))
    args = parser.parse_args(argv)
    steps, repeats = (300, 3) if args.quick else (1000, 5)

    env = InsertionEnv("gear")
    state, tau = seated_state(env)
    free_env = InsertionEnv("free")
    free_state = np.zeros(mujoco.mj_stateSize(free_env.model, STATE_SPEC))
    mujoco.mj_getState(free_env.model, free_env.data, free_state, STATE_SPEC)

    results = {
        "what": "gear scene, gear seated and pushed onto the shoulder (contacts active); steps/s medians",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(), "mujoco": mujoco.__version__},
        "steps_per_repeat": steps,
        "repeats": repeats,
        "single_env_contact": bench_single(env, state, tau, steps, repeats),
        "single_env_free_space": bench_single(free_env, free_state, free_env.bias_torques, steps, repeats),
        "batched": [bench_batched(n, t, state, tau, max(steps // 4, 50), repeats)
                    for n, t in ((16, 1), (16, 2), (32, 2))],
        "rollout_closed_loop": [bench_rollout(env.model, 16, 2, state, tau, max(steps // 4, 50), repeats)],
    }
    best = max(results["batched"], key=lambda r: r["env_steps_per_s"] if r["n_threads"] == 2 else 0)
    results["summary"] = {
        "single_env_steps_per_s": round(results["single_env_contact"]["env_step_per_s"]),
        "batched_2_threads_steps_per_s": round(best["env_steps_per_s"]),
        "target_batched_steps_per_s": 30000,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2))
    print(json.dumps(results, indent=2))
    return results


if __name__ == "__main__":
    main()
