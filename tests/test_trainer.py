"""Rollouts (reward terms, held noise, determinism), exact checkpoint resume, and learning on the block task."""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from learner_node.config import TrainConfig
from learner_node.flow import rescale_flow_weights
from learner_node.rollout import RolloutRunner
from learner_node.train_cli import main as train_main
from learner_node.trainer import (
    CHECKPOINT,
    CHECKPOINT_FORMAT,
    EVAL_SEED_BASE,
    EVALUATION_FILE,
    PRIOR_EVALUATION_FILE,
    Trainer,
    build_policy,
    make_evaluator,
    metrics_without_timing,
    policy_sigma,
    run_evaluations,
)
from nf_core.reward import REWARD_TERMS, RewardWeights, reward_terms

TINY = {"task": "block", "iterations": 2, "rollouts_per_iter": 3, "episode_seconds": 0.2, "minibatch_size": 16,
        "update_epochs": 2, "eval_episodes": 2}
GEAR_LEARN = Path(__file__).resolve().parents[1] / "config" / "gear_learn.yaml"
GEAR_TINY = {"iterations": 1, "rollouts_per_iter": 2, "episode_seconds": 0.05, "eval_episodes": 1}


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Tiny tensors: intra-op threads only add spin-waiting on these shared 2-core machines."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_reward_terms_hand_computed():
    terms = reward_terms(np.array([0.003, 0.004]), np.array([1.0, 0.0]), np.array([10.0, 0.0]), RewardWeights())
    assert terms["distance"] == pytest.approx(-2.5e-5, rel=1e-12)
    assert terms["log_distance"] == pytest.approx(-2.0 * math.log(3.5), rel=1e-12)  # (2.5e-5 + 1e-5) / 1e-5
    assert terms["velocity"] == pytest.approx(-0.1, rel=1e-12)
    assert terms["action"] == pytest.approx(-0.1, rel=1e-12)
    at_goal = reward_terms(np.zeros(3), np.zeros(3), np.zeros(3), RewardWeights())
    assert all(v == 0.0 for v in at_goal.values())


def _episode(cfg: TrainConfig, start_seed: int, noise_seed: int):
    runner = RolloutRunner(cfg)
    policy = build_policy(cfg, runner.x_ref)
    sigma = policy_sigma(policy)
    rec = runner.run_episode(make_evaluator(policy), sigma, start_seed, np.random.default_rng(noise_seed))
    return runner, policy, sigma, rec


@pytest.mark.parametrize(("task", "policy"), [("block", "nf"), ("block", "mlp"), ("gear", "nf"), ("gear", "mlp")])
def test_rollout_terms_noise_log_prob_and_determinism(task, policy):
    cfg = TrainConfig(task=task, policy=policy, episode_seconds=0.05 if task == "gear" else 0.2)
    runner, pol, sigma, rec = _episode(cfg, start_seed=11, noise_seed=7)
    K, d = cfg.decisions_per_episode, cfg.dim
    # the reward terms are reported separately and sum to the reward
    np.testing.assert_allclose(np.sum([rec.terms[n] for n in REWARD_TERMS], axis=0), rec.reward, rtol=0, atol=1e-12)
    assert all(np.all(rec.terms[n] <= 0.0) for n in REWARD_TERMS)
    # one noise draw per decision, from the given generator, held for the period
    noise = sigma * np.random.default_rng(7).standard_normal((K, d))
    np.testing.assert_allclose(rec.action - rec.u_mean, noise, rtol=0, atol=1e-12)
    # the recorded behaviour log-probabilities are the torch policy's (evaluator == torch)
    with torch.no_grad():
        lp = pol.log_prob(torch.from_numpy(rec.x), torch.from_numpy(rec.xdot), torch.from_numpy(rec.action))
        u = pol.mean_force(torch.from_numpy(rec.x), torch.from_numpy(rec.xdot))
    np.testing.assert_allclose(rec.log_prob, lp.numpy(), rtol=0, atol=1e-9)
    np.testing.assert_allclose(rec.u_mean, u.numpy(), rtol=0, atol=1e-9)
    assert rec.x.shape == (K, d) and np.isfinite(rec.torque_norm) and rec.faults == 0
    # same seeds: the same episode, bit for bit; another start seed: another episode
    again = runner.run_episode(make_evaluator(pol), sigma, 11, np.random.default_rng(7))
    for name in ("x", "xdot", "action", "reward", "depth"):
        np.testing.assert_array_equal(getattr(again, name), getattr(rec, name))
    other = runner.run_episode(make_evaluator(pol), sigma, 12, np.random.default_rng(7))
    assert not np.array_equal(other.x[0], rec.x[0])


def test_evaluation_is_deterministic_from_held_out_starts():
    trainer = Trainer(TrainConfig(**TINY))
    first, second = trainer.evaluate(), trainer.evaluate()
    assert [e["start_seed"] for e in first["per_episode"]] == [EVAL_SEED_BASE, EVAL_SEED_BASE + 1]
    assert first["per_episode"] == second["per_episode"]


def _cli(out, iterations: int) -> int:
    sets = [f"--set={k}={v}" for k, v in TINY.items() if k not in ("task", "iterations")]
    return train_main(["--task", "block", "--out", str(out), "--iterations", str(iterations), "--no-progress",
                       "--no-eval", *sets])


def test_checkpoint_resume_reproduces_the_next_iteration_exactly(tmp_path):
    straight = Trainer(TrainConfig(**TINY), tmp_path / "straight")
    straight.run(evaluate=False)
    # the same run interrupted after one iteration and resumed by the CLI from its checkpoint
    assert _cli(tmp_path / "resumed", 1) == 0
    assert _cli(tmp_path / "resumed", 2) == 0
    a = torch.load(tmp_path / "straight" / CHECKPOINT, weights_only=True)
    b = torch.load(tmp_path / "resumed" / CHECKPOINT, weights_only=True)
    assert a["iteration"] == b["iteration"] == 2
    assert [metrics_without_timing(r) for r in a["history"]] == [metrics_without_timing(r) for r in b["history"]]
    for key, value in a["policy"].items():
        assert torch.equal(value, b["policy"][key]), key
    for key, value in a["optimizer"]["state"].items():
        for name, tensor in value.items():
            assert torch.equal(tensor, b["optimizer"]["state"][key][name]), (key, name)
    assert a["rng"] == b["rng"]
    rows = list(csv.DictReader((tmp_path / "resumed" / "metrics.csv").open()))
    assert [float(r["iteration"]) for r in rows] == [1.0, 2.0]
    assert len(json.loads((tmp_path / "resumed" / "metrics.json").read_text())) == 2


def test_the_prior_is_evaluated_first_on_the_final_starts_without_changing_the_training(tmp_path):
    """``train`` shows where a run began: the untrained policy on the final evaluation's held-out
    starts (evaluation_prior.json, iteration 0), as the learner node does over ROS. It draws nothing
    from the training's random streams: the run that follows is the one without it, to the bit; a
    resumed run does not repeat it."""
    sets = [f"--set={k}={v}" for k, v in TINY.items() if k not in ("task", "iterations")]
    cli = ["--task", "block", "--iterations", "2", "--no-progress", *sets]
    assert train_main([*cli, "--out", str(tmp_path / "with")]) == 0
    assert train_main([*cli, "--out", str(tmp_path / "without"), "--no-prior-eval"]) == 0
    prior = json.loads((tmp_path / "with" / PRIOR_EVALUATION_FILE).read_text())
    final = json.loads((tmp_path / "with" / EVALUATION_FILE).read_text())
    assert not (tmp_path / "without" / PRIOR_EVALUATION_FILE).exists()
    assert prior["iteration"] == 0 and final["iteration"] == 2 and prior["episodes"] == TINY["eval_episodes"]
    assert [e["start_seed"] for e in prior["per_episode"]] == [e["start_seed"] for e in final["per_episode"]]
    assert prior["per_episode"] != final["per_episode"]  # the policy did change in between
    histories = [json.loads((tmp_path / run / "metrics.json").read_text()) for run in ("with", "without")]
    assert [metrics_without_timing(r) for r in histories[0]] == [metrics_without_timing(r) for r in histories[1]]
    assert json.loads((tmp_path / "without" / EVALUATION_FILE).read_text())["per_episode"] == final["per_episode"]
    assert [label for label, _ in run_evaluations(tmp_path / "with")] == [
        "the prior (before iteration 1)", "learned (after iteration 2)"]
    (tmp_path / "with" / PRIOR_EVALUATION_FILE).unlink()  # a resume (here: to iteration 3) does not redo it
    assert train_main([*cli[:2], *cli[4:], "--iterations", "3", "--out", str(tmp_path / "with")]) == 0
    assert not (tmp_path / "with" / PRIOR_EVALUATION_FILE).exists()
    assert json.loads((tmp_path / "with" / EVALUATION_FILE).read_text())["iteration"] == 3


def test_resume_refuses_a_checkpoint_of_other_settings(tmp_path):
    Trainer(TrainConfig(**{**TINY, "iterations": 1}), tmp_path).run(evaluate=False)
    other = Trainer(TrainConfig(**{**TINY, "seed": 1}))
    with pytest.raises(ValueError, match="seed: checkpoint 0 vs now 1"):
        other.load_checkpoint(tmp_path / CHECKPOINT)


def test_a_checkpoint_from_before_a_new_setting_resumes_with_its_default(tmp_path):
    """flow_init came after the first runs: their checkpoints lack it and meant the default (random)."""
    Trainer(TrainConfig(**{**TINY, "iterations": 1}), tmp_path).run(evaluate=False)
    state = torch.load(tmp_path / CHECKPOINT, weights_only=True)
    del state["config"]["flow_init"]
    resumed = Trainer(TrainConfig(**TINY))
    resumed.load_state_dict(state)
    assert resumed.iteration == 1
    with pytest.raises(ValueError, match="flow_init: checkpoint 'random' vs now 'identity'"):
        Trainer(TrainConfig(**{**TINY, "flow_init": "identity"})).load_state_dict(state)


def test_an_mlp_checkpoint_ignores_flow_settings(tmp_path):
    """The MLP policy never reads the flow's settings, so a task file's new flow_init must not stop its resume."""
    Trainer(TrainConfig(**{**TINY, "policy": "mlp", "iterations": 1}), tmp_path).run(evaluate=False)
    resumed = Trainer(TrainConfig(**{**TINY, "policy": "mlp", "flow_init": "identity", "stiffness": 50.0}))
    resumed.load_checkpoint(tmp_path / CHECKPOINT)
    assert resumed.iteration == 1


def test_a_new_run_starts_from_another_runs_checkpoint_with_its_own_goal(tmp_path, caplog):
    """init_checkpoint (issue 30): a policy learned in simulation starts a run on a cell whose goal
    differs. Loaded: the flow, S, D and the exploration spread as the checkpoint left them (not the
    config's param_sigma_*); fresh: the iteration, optimiser and metrics; x_ref is the new goal. The
    prior evaluated first is that policy and says where it came from; rerun, the run resumes its own."""
    source = Trainer(TrainConfig.from_sources(GEAR_LEARN, GEAR_TINY), tmp_path / "sim")
    source.run(evaluate=False)
    ckpt = tmp_path / "sim" / CHECKPOINT
    goal = [0.52, 0.03, 0.05]  # the simulated gear's is [0.5, 0, 0.07]
    cfg = TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "goal": goal, "init_checkpoint": str(ckpt)})
    run = Trainer(cfg, tmp_path / "robot")
    note = run.resume_or_init()
    assert note.startswith(f"starting a new run from {ckpt}") and "x_ref [0.52, 0.03, 0.05]" in note
    assert run.iteration == 0 and run.history == [] and run.optimizer.state_dict()["state"] == {}
    mine, theirs = run.policy.to_params(), source.policy.to_params()
    # the landscape belongs to the goal (the nets see (x - x_ref) / flow_input_scale): the same
    # normalised weights, physical ones moved with the goal
    arch, scale = run.policy.flow.arch, cfg.flow_input_scale
    assert scale > 0 and not np.allclose(mine.weights, theirs.weights)
    np.testing.assert_allclose(rescale_flow_weights(arch, mine.weights, goal, scale, inverse=True),
                               rescale_flow_weights(arch, theirs.weights, theirs.x_ref, scale, inverse=True),
                               atol=1e-12)
    x = np.array([[0.01, -0.02, 0.03], [0.0, 0.0, 0.0], [-0.03, 0.01, 0.02]])  # offsets from the goal, m
    with torch.no_grad():  # phi(x_ref + e) - phi(x_ref) is the same landscape around either goal
        mov, src = run.policy.flow, source.policy.flow
        a = mov(torch.as_tensor(goal + x)) - mov(torch.as_tensor(np.array([goal])))
        b = src(torch.as_tensor(theirs.x_ref + x)) - src(torch.as_tensor(theirs.x_ref[None]))
    np.testing.assert_allclose(a.numpy(), b.numpy(), atol=5e-3)
    np.testing.assert_allclose(mine.stiffness, theirs.stiffness, rtol=1e-12)
    np.testing.assert_allclose(mine.damping, theirs.damping, rtol=1e-12)
    assert not np.allclose(np.diag(mine.stiffness), cfg.stiffness)  # learned, not the config's 300 N/m
    np.testing.assert_array_equal(mine.log_std, theirs.log_std)
    np.testing.assert_allclose(mine.x_ref, goal)
    np.testing.assert_allclose(theirs.x_ref, [0.5, 0.0, 0.07])
    for name in ("log_sigma_gains", "log_sigma_flow"):  # the spread goes on, decayed: not param_sigma_*
        assert torch.equal(getattr(run.explorer, name), getattr(source.explorer, name)), name
    assert float(torch.exp(run.explorer.log_sigma_gains.detach()).max()) < cfg.param_sigma_gains
    centre = run.explorer.params_for(run.explorer.mean().detach().numpy())  # draws centre on the loaded flow
    np.testing.assert_allclose(centre.weights, mine.weights, rtol=0, atol=1e-12)
    # the CLI: the prior is the loaded policy (the zero-shot result) and says so; the same command resumes
    sets = [f"--set={k}={v}" for k, v in GEAR_TINY.items()]
    cli = ["--config", str(GEAR_LEARN), "--out", str(tmp_path / "cli"), "--init-checkpoint", str(ckpt),
           "--set=goal=0.52,0.03,0.05", "--no-progress", *sets]
    assert train_main(cli) == 0
    prior = json.loads((tmp_path / "cli" / PRIOR_EVALUATION_FILE).read_text())
    assert prior["iteration"] == 0 and prior["started_from"]["checkpoint"] == str(ckpt.resolve())
    assert prior["per_episode"] == run.evaluate()["per_episode"]
    assert json.loads((tmp_path / "cli" / EVALUATION_FILE).read_text())["started_from"] == prior["started_from"]
    assert run_evaluations(tmp_path / "cli")[0][0] == f"the prior, started from {ckpt.resolve()} (before iteration 1)"
    caplog.clear()
    with caplog.at_level(logging.INFO):
        assert train_main(cli) == 0
    assert f"resuming from {tmp_path / 'cli' / CHECKPOINT} after iteration 1" in caplog.text
    assert "the run folder's own checkpoint wins" in caplog.text


def test_init_checkpoint_refuses_another_architecture_and_a_missing_file(tmp_path, capsys):
    Trainer(TrainConfig(**{**TINY, "iterations": 1}), tmp_path / "a").run(evaluate=False)
    ckpt = str(tmp_path / "a" / CHECKPOINT)
    for change, message in (({"n_hidden": 4}, "n_hidden: checkpoint 8 vs now 4"),
                            ({"policy": "mlp"}, "policy: checkpoint 'nf' vs now 'mlp'"),
                            ({"task": "gear"}, r"dimension: checkpoint 2 \(task block\) vs now 3 \(task gear\)")):
        trainer = Trainer(TrainConfig(**{**TINY, **change, "init_checkpoint": ckpt}), tmp_path / "b")
        with pytest.raises(ValueError, match=f"another architecture than this config's .*{message}"):
            trainer.resume_or_init()
    (tmp_path / "junk.pt").write_text("not a checkpoint")
    for path, message in ((tmp_path / "none.pt", "no such file"), (tmp_path / "junk.pt", "not a readable checkpoint"),
                          (tmp_path / "a", "is not a file")):
        with pytest.raises(ValueError, match=message):
            Trainer(TrainConfig(**{**TINY, "init_checkpoint": str(path)}), tmp_path / "b").resume_or_init()
    sets = [f"--set={k}={v}" for k, v in TINY.items() if k != "task"]
    assert train_main(["--task", "block", "--out", str(tmp_path / "c"), "--init-checkpoint", str(tmp_path / "none.pt"),
                       "--no-progress", *sets]) == 2
    assert f"init_checkpoint {tmp_path / 'none.pt'}: no such file" in capsys.readouterr().err
    assert not (tmp_path / "b").exists() and not (tmp_path / "c").exists()  # refused before anything is written
    # an MLP policy moves with its goal by itself (it sees x - x_ref): loaded as learned
    Trainer(TrainConfig(**{**TINY, "policy": "mlp", "iterations": 1}), tmp_path / "m").run(evaluate=False)
    mlp = Trainer(TrainConfig(**{**TINY, "policy": "mlp", "goal": [0.1, 0.2],
                                 "init_checkpoint": str(tmp_path / "m" / CHECKPOINT)}))
    assert "action noise std" in mlp.resume_or_init()
    theirs = torch.load(tmp_path / "m" / CHECKPOINT, weights_only=True)
    assert theirs["format"] == CHECKPOINT_FORMAT
    for key, value in mlp.policy.state_dict().items():
        if key == "x_ref":
            np.testing.assert_allclose(value.numpy(), [0.1, 0.2])
        else:
            assert torch.equal(value, theirs["policy"][key]), key


def test_mlp_policy_iterations_run(tmp_path):
    for extra in ({"policy": "mlp"},):
        trainer = Trainer(TrainConfig(**{**TINY, "iterations": 1, **extra}), tmp_path / next(iter(extra.values())))
        result = trainer.run()
        row = trainer.history[-1]
        assert all(np.isfinite(v) for k, v in row.items() if k != "v_loss")
        assert result is not None and result["episodes"] == 2
        assert (tmp_path / next(iter(extra.values())) / "evaluation.json").exists()


def test_short_block_training_improves_return():
    """12 iterations of NF-PPO on block insertion (6 rollouts of 2 s, larger steps than the paper's so it
    fits a test). Measured (seed 0/1/2): deterministic return on 6 held-out starts -3068/-3347/-3037 before,
    about -2700 after; the mean training return rises from about -3370 to about -2750."""
    cfg = TrainConfig(task="block", iterations=12, rollouts_per_iter=6, episode_seconds=2.0, minibatch_size=256,
                      update_epochs=5, learning_rate=3e-3, eval_episodes=6, seed=0)
    trainer = Trainer(cfg)
    before = trainer.evaluate()["return_mean"]
    trainer.run(evaluate=False)
    after = trainer.evaluate()["return_mean"]
    returns = [r["return_mean"] for r in trainer.history]
    assert after > before + 0.05 * abs(before), (before, after)
    assert np.mean(returns[-3:]) > np.mean(returns[:3]) + 0.05 * abs(np.mean(returns[:3])), returns


def test_deploy_moves_the_flow_with_the_goal_as_the_learner_does(tmp_path):
    """deploy_policy --x-ref and init_checkpoint give the same policy for a goal: the flow's landscape
    (nets that see (x - x_ref) / flow_input_scale) moves with x_ref."""
    from learner_node.deploy import load_checkpoint_policy, prepare

    Trainer(TrainConfig.from_sources(GEAR_LEARN, GEAR_TINY), tmp_path / "sim").run(evaluate=False)
    ckpt = tmp_path / "sim" / CHECKPOINT
    goal = [0.5, 0.0, 0.05]
    params, iteration, scale = load_checkpoint_policy(ckpt)
    assert iteration == 1 and scale > 0
    deployed = prepare(params, goal, None, scale)
    learner = Trainer(TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "goal": goal, "init_checkpoint": str(ckpt)}),
                      tmp_path / "robot")
    learner.resume_or_init()
    np.testing.assert_allclose(deployed.weights, learner.policy.to_params().weights, rtol=0, atol=1e-12)
    np.testing.assert_allclose(deployed.x_ref, goal)
    kept = prepare(load_checkpoint_policy(ckpt)[0], None, None, scale)  # --keep-x-ref: as learned
    np.testing.assert_allclose(kept.x_ref, [0.5, 0.0, 0.07])
    assert not np.allclose(kept.weights, deployed.weights)
    # --stiffness-floor lifts S as the learner's stiffness_floor lifts a loaded policy
    soft = Trainer(TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "stiffness_axial": 120.0}), tmp_path / "soft")
    soft.save_checkpoint(tmp_path / "soft.pt")
    lifted = prepare(load_checkpoint_policy(tmp_path / "soft.pt")[0], goal, None, scale, stiffness_floor=250.0)
    np.testing.assert_allclose(np.diag(lifted.stiffness), [300.0, 300.0, 250.0])
    floored = Trainer(TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "goal": goal, "stiffness_floor": 250.0,
                                                            "init_checkpoint": str(tmp_path / "soft.pt")}),
                      tmp_path / "robot2")
    floored.resume_or_init()
    np.testing.assert_allclose(lifted.stiffness, floored.policy.to_params().stiffness, rtol=1e-12)
    np.testing.assert_allclose(lifted.weights, floored.policy.to_params().weights, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="stiffness floor must be >= 0"):
        prepare(load_checkpoint_policy(ckpt)[0], goal, None, scale, stiffness_floor=-1.0)


def test_fine_tuning_updates_stop_at_init_target_kl(tmp_path):
    """From a checkpoint the updates use init_target_kl (a loaded policy is kept near); a new run target_kl."""
    Trainer(TrainConfig.from_sources(GEAR_LEARN, GEAR_TINY), tmp_path / "sim").run(evaluate=False)
    ckpt = str(tmp_path / "sim" / CHECKPOINT)
    epochs = {}
    for kl in (0.0, 1e-12):
        tuned = Trainer(TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "iterations": 1, "init_checkpoint": ckpt,
                                                              "init_target_kl": kl}), tmp_path / f"kl{kl}")
        tuned.resume_or_init()
        tuned.run(evaluate=False)
        epochs[kl] = tuned.history[-1]["epochs"]
    assert epochs[0.0] == TrainConfig.from_sources(GEAR_LEARN, {}).update_epochs and epochs[1e-12] < epochs[0.0], epochs
    assert TrainConfig.from_sources(GEAR_LEARN, {"init_checkpoint": ckpt}).update_target_kl == 0.02
    assert TrainConfig.from_sources(GEAR_LEARN, {}).update_target_kl == 0.0
    with pytest.raises(ValueError, match="init_target_kl"):
        TrainConfig.from_sources(GEAR_LEARN, {"init_target_kl": -1.0})


def test_eval_every_evaluates_the_deterministic_controller_between_iterations_without_changing_training(tmp_path):
    """``eval_every=2``: after iterations 2 and 4 the deterministic controller runs on the held-out starts
    (metrics columns, evaluations/iteration_NNNN.json, markers on the curves); the training is the one
    without it to the bit, and the final evaluation is the last periodic one, not a second run."""
    sets = [f"--set={k}={v}" for k, v in TINY.items() if k not in ("task", "iterations")]
    cli = ["--task", "block", "--iterations", "4", "--no-progress", "--no-prior-eval", *sets]
    assert train_main([*cli, "--set", "eval_every=2", "--out", str(tmp_path / "every")]) == 0
    assert train_main([*cli, "--out", str(tmp_path / "plain")]) == 0
    every, plain = (json.loads((tmp_path / r / "metrics.json").read_text()) for r in ("every", "plain"))
    eval_cols = ("eval_return", "eval_success", "eval_final_distance")
    assert [{k: v for k, v in metrics_without_timing(r).items() if k not in eval_cols} for r in every] == [
        metrics_without_timing(r) for r in plain]
    assert all(k not in plain[0] for k in eval_cols)
    evaluated = [int(r["iteration"]) for r in every if math.isfinite(r["eval_success"])]
    assert evaluated == [2, 4]
    files = sorted(p.name for p in (tmp_path / "every" / "evaluations").iterdir())
    assert files == ["iteration_0002.json", "iteration_0004.json"]
    at2 = json.loads((tmp_path / "every" / "evaluations" / files[0]).read_text())
    assert at2["iteration"] == 2 and at2["episodes"] == TINY["eval_episodes"]
    assert every[1]["eval_final_distance"] == pytest.approx(at2["final_distance_mean"])
    final = json.loads((tmp_path / "every" / EVALUATION_FILE).read_text())
    assert final == json.loads((tmp_path / "every" / "evaluations" / files[1]).read_text())
    assert final["per_episode"] == json.loads((tmp_path / "plain" / EVALUATION_FILE).read_text())["per_episode"]
    rows = list(csv.DictReader((tmp_path / "every" / "metrics.csv").open()))
    assert rows[0]["eval_success"] == "nan" and rows[1]["eval_success"] != "nan"


def test_a_run_resumed_with_periodic_evaluations_keeps_writing_its_metrics(tmp_path):
    """Resumed with ``eval_every`` on, a run's later rows have columns its first rows lack: metrics.csv
    gets them all (blank where a row has none), where it used to stop the run with a ValueError."""
    sets = [f"--set={k}={v}" for k, v in TINY.items() if k not in ("task", "iterations")]
    cli = ["--task", "block", "--no-progress", "--no-prior-eval", "--no-eval", *sets, "--out", str(tmp_path)]
    assert train_main([*cli, "--iterations", "1"]) == 0
    assert train_main([*cli, "--iterations", "2", "--set", "eval_every=1"]) == 0
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [r["iteration"] for r in rows] == ["1.0", "2.0"]
    assert rows[0]["eval_success"] == "" and math.isfinite(float(rows[1]["eval_success"]))


def test_periodic_evaluations_give_the_mean_over_seeds_where_they_ran():
    from learner_node.analysis.plots import periodic_evaluations

    nan = math.nan
    a = [{"iteration": 1, "eval_success": nan}, {"iteration": 2, "eval_success": 0.5}]
    b = [{"iteration": 1, "eval_success": nan}, {"iteration": 2, "eval_success": 1.0}]
    its, mean = periodic_evaluations([a, b], "success_rate")
    assert its.tolist() == [2.0] and mean.tolist() == [0.75]
    assert periodic_evaluations([[{"iteration": 1}]], "success_rate")[0].size == 0


def test_fresh_removes_the_earlier_runs_results(tmp_path, caplog):
    """``--fresh`` starts over in the same folder: the earlier run's prior and final evaluations and
    periodic ones go, so the new run's folder (its curves, a summary) shows only its own results."""
    sets = [f"--set={k}={v}" for k, v in TINY.items() if k not in ("task", "iterations")]
    cli = ["--task", "block", "--iterations", "2", "--no-progress", *sets, "--out", str(tmp_path)]
    assert train_main([*cli, "--set", "eval_every=1"]) == 0
    assert (tmp_path / PRIOR_EVALUATION_FILE).exists() and (tmp_path / "evaluations" / "iteration_0001.json").exists()
    with caplog.at_level(logging.INFO):
        assert train_main([*cli, "--fresh", "--no-prior-eval", "--no-eval"]) == 0
    assert "removed the earlier run's" in caplog.text and PRIOR_EVALUATION_FILE in caplog.text
    assert not (tmp_path / PRIOR_EVALUATION_FILE).exists() and not (tmp_path / EVALUATION_FILE).exists()
    assert list((tmp_path / "evaluations").glob("*.json")) == []
    assert [r["iteration"] for r in json.loads((tmp_path / "metrics.json").read_text())] == [1.0, 2.0]


def test_stiffness_floor_bounds_every_draw_the_mean_and_a_loaded_policy(tmp_path, caplog):
    """stiffness_floor (the arm's joint friction stalls a soft spring): no draw, no mean and no policy
    loaded from a checkpoint runs an S entry below it; what is refused is said."""
    source = Trainer(TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "stiffness_axial": 120.0}), tmp_path / "sim")
    assert float(source.policy.to_params().stiffness[2, 2]) == pytest.approx(120.0)
    source.save_checkpoint(tmp_path / "soft.pt")
    cfg = TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "stiffness_floor": 250.0,
                                                "init_checkpoint": str(tmp_path / "soft.pt")})
    run = Trainer(cfg, tmp_path / "arm")
    with caplog.at_level(logging.INFO):
        run.resume_or_init()
    assert "stiffness [300.0, 300.0, 120.0] N/m lifted to stiffness_floor 250 N/m (entries [2])" in caplog.text
    s = np.diag(run.policy.to_params().stiffness)
    assert s[2] == pytest.approx(250.0) and s[:2] == pytest.approx([300.0, 300.0])
    draws, _ = run.explorer.sample(64, np.random.default_rng(1))
    stiff = np.array([np.diag(run.explorer.params_for(t).stiffness) for t in draws])
    assert stiff.min() == pytest.approx(250.0) and (np.exp(draws[:, :3]) < 250.0).any()  # some were lifted
    with torch.no_grad():  # a mean below the floor (an update may move it there) still runs the floor
        run.policy.ln_s[0] = math.log(100.0)
    assert np.diag(run.policy.to_params().stiffness)[0] == pytest.approx(250.0)
    with pytest.raises(ValueError, match="starts below stiffness_floor"):
        Trainer(TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "stiffness_floor": 400.0}))
    with pytest.raises(ValueError, match="stiffness_floor needs the nf policy with gains: learned"):
        TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "stiffness_floor": 250.0, "gains": "fixed"})
    with pytest.raises(ValueError, match="stiffness_floor"):
        TrainConfig.from_sources(GEAR_LEARN, {**GEAR_TINY, "stiffness_floor": -1.0})
