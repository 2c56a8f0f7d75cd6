"""The decision-level view of the training task (``DecisionEnv``) and its Gymnasium wrapper against the rollout.

A rollout with a zero mean force applies exactly its held noise; stepping the environments with that
episode's actions from the same start must reproduce its states, rewards and depths. The gymnasium
parts skip when gymnasium (a bench-only dependency, requirements/bench.txt) is not installed.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from learner_node.analysis.decision_env import DecisionEnv, ZeroForce
from learner_node.config import TrainConfig
from learner_node.rollout import EpisodeRecord, RolloutRunner

ROOT = Path(__file__).resolve().parents[1]
START_SEED, NOISE_SEED = 7, 3
TOL = 1e-9


def short_config(task: str) -> TrainConfig:
    """The task's config file, with 0.3 s episodes (30 decisions of 10 ms)."""
    return TrainConfig.from_sources(ROOT / "config" / f"{task}.yaml", {"episode_seconds": 0.3})


def zero_mean_rollout(cfg: TrainConfig) -> EpisodeRecord:
    """The trainer's rollout with a zero mean force: its actions are its held noise (std 5 N)."""
    runner = RolloutRunner(cfg)
    return runner.run_episode(ZeroForce(cfg.dim), np.full(cfg.dim, 5.0), START_SEED,
                              np.random.default_rng(NOISE_SEED))


def check_replay(rec: EpisodeRecord, x_ref: np.ndarray, first_obs: np.ndarray,
                 step: Callable[[np.ndarray], tuple[np.ndarray, float, bool, dict]]) -> None:
    """Step with the rollout's actions; observations, rewards, depths and the episode end must match it."""
    K = len(rec.reward)
    want_obs = np.concatenate([rec.x - x_ref, rec.xdot], axis=1)
    np.testing.assert_allclose(first_obs, want_obs[0], rtol=0, atol=TOL)
    torque = []
    for k in range(K):
        obs, reward, over, info = step(rec.action[k])
        assert reward == pytest.approx(rec.reward[k], rel=0, abs=TOL), k
        assert info["depth"] == pytest.approx(rec.depth[k], rel=0, abs=TOL)
        assert info["success"] == rec.success[k]
        assert over == (k == K - 1)
        torque.append(info["torque_norm"])
        if k + 1 < K:
            np.testing.assert_allclose(obs, want_obs[k + 1], rtol=0, atol=TOL, err_msg=f"decision {k + 1}")
    assert np.mean(torque) == pytest.approx(rec.torque_norm, rel=1e-12)


@pytest.mark.parametrize("task", ["gear", "block"])
def test_decision_env_replays_the_rollout(task):
    cfg = short_config(task)
    rec = zero_mean_rollout(cfg)
    assert np.ptp(rec.x, axis=0).max() > 1e-3  # the noise moved it: the comparison is not trivial
    env = DecisionEnv(cfg)
    assert env.horizon == cfg.decisions_per_episode == len(rec.reward)
    check_replay(rec, env.runner.x_ref, env.reset(START_SEED), env.step)
    with pytest.raises(RuntimeError, match="call reset"):  # past the time limit: a clear error, no IndexError
        env.step(rec.action[0])
    again = env.reset(START_SEED)  # a second episode in the same env starts the same
    np.testing.assert_array_equal(again, np.concatenate([rec.x[0] - env.runner.x_ref, rec.xdot[0]]))


def test_gym_env_replays_the_rollout_and_passes_the_checker():
    pytest.importorskip("gymnasium", reason="gymnasium is a bench-only dependency (requirements/bench.txt)")
    from gymnasium.utils.env_checker import check_env

    from learner_node.analysis.gym_env import InsertionGymEnv

    cfg = short_config("gear")
    env = InsertionGymEnv(cfg)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env, skip_render_check=True)
    expected = ("infinity. This is probably too", "symmetric and normalized space")  # unbounded obs, force in N
    unexpected = [str(w.message) for w in caught if not any(e in str(w.message) for e in expected)]
    assert not unexpected, unexpected

    rec = zero_mean_rollout(cfg)
    obs, info = env.reset(seed=START_SEED)
    assert info["start_seed"] == START_SEED and obs in env.observation_space

    def step(action: np.ndarray) -> tuple[np.ndarray, float, bool, dict]:
        obs, reward, terminated, truncated, info = env.step(action)
        assert not terminated and isinstance(reward, float)
        return obs, reward, truncated, info

    check_replay(rec, env.core.runner.x_ref, obs, step)
    unseeded = [env.reset()[1]["start_seed"] for _ in range(2)]  # unseeded resets draw new training starts
    assert unseeded[0] != unseeded[1]
