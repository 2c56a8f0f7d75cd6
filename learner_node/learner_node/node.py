"""learner_node: NF-PPO over ROS 2. Drives episodes through the controller's ``run_episode``
action, assembles the streamed rollouts (``rollouts``), runs the trainer's PPO update and
publishes the new policy on ``/policy_parameters`` (reliable, transient local, version =
completed iterations).

The training settings are the task's parameters file (the ``/**`` and ``learner_node``
sections), exactly what ``train --config`` reads, so an in-process run and a run over ROS with
the same file and seed draw the same starts and noise. ``out_dir`` gets the same metrics,
checkpoint and evaluation files as ``train``, and (``evaluate_prior``) ``evaluation_prior.json``:
the deterministic prior on the same held-out starts before the first iteration, so a run shows
what it learned against where it began. A restarted learner resumes from the checkpoint
and repeats the interrupted iteration with the same seeds. Episodes that fail or arrive
incomplete are reported and retried with the same seeds, then dropped.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from pathlib import Path
from typing import Any

import rclpy
from nf_msgs.action import RunEpisode
from nf_msgs.msg import ControllerStatus, RolloutChunk
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from rclpy.action import ActionClient
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from nf_core import qos
from nf_core.policy_params import PolicyParameters
from nf_core.ros_runtime import SpinLock, run_node
from nf_core.topics import CONTROLLER_STATUS, POLICY_PARAMETERS, ROLLOUTS, RUN_EPISODE

from .config import TrainConfig
from .rollout import EpisodeRecord
from .ros_episodes import ChunkCollector, IncompleteEpisodeError, episode_from_chunks
from .trainer import (
    CHECKPOINT,
    EVAL_SEED_BASE,
    EVALUATION_FILE,
    PRIOR_EVALUATION_FILE,
    Trainer,
    _atomic_write,
    _json_float,
    episode_summary,
)

LOG = logging.getLogger("learner_node")
ROLLOUT_VERSIONS = 1000  # parameter exploration: policy versions per iteration (one per rollout)
NODE_PARAMETERS = {  # learner_node's own settings besides TrainConfig's
    "out_dir": "runs/ros",
    "episode_timeout": 120.0,  # s of wall time for one episode (lockstep runs at a few x real time)
    "episode_retries": 2,  # an incomplete episode is run again this often (same seeds), then dropped
    "server_timeout": 60.0,  # s to wait for the controller's action server
    # A controller in safe hold (a latched fault) fails every episode until the fault is cleared.
    # "wait": wait for a person to call nf_controller/clear_fault (hardware), then go on;
    # "auto": clear it at once (simulation only: the next reset puts the arm somewhere new).
    "on_safe_hold": "wait",
    "clear_fault_service": "nf_controller/clear_fault",
    # Subscribers of /policy_parameters to wait for before the first episode (the controller; 2 with
    # a bag recorder, which subscribes only once it sees this publisher: a short run could end
    # before it did, and the bag would hold no policy). Waited for at most server_timeout.
    "policy_subscribers": 1,
    "policy_ack_timeout": 5.0,  # s to wait at the end for every subscriber to acknowledge the last policy
    # Before the first iteration, the deterministic prior on the same eval_episodes held-out starts as
    # the final evaluation (evaluation_prior.json): what the run learned is then shown, not assumed.
    "evaluate_prior": True,
}
ON_SAFE_HOLD = ("wait", "auto")
AUTO_CLEARS_PER_EPISODE = 3  # "auto": an episode that faults this often after clearing is dropped
_FIELDS = {f for f in TrainConfig.__dataclass_fields__}


class EpisodeFailedError(RuntimeError):
    """An episode the controller did not complete, or whose rollout did not fully arrive."""


class LearnerNode(Node):
    """The ROS side of the learner: the action client, the chunk subscription, the policy publisher."""

    def __init__(self) -> None:
        super().__init__("learner_node", automatically_declare_parameters_from_overrides=True)
        overrides: dict[str, Any] = {}
        for name, param in self._parameters.items():
            if name in _FIELDS:
                overrides[name] = param.value
        self.settings = {k: self.get_parameter_or(k, rclpy.Parameter(k, value=v)).value
                         for k, v in NODE_PARAMETERS.items()}
        self.cfg = TrainConfig.from_sources(None, overrides)
        if self.cfg.policy != "nf":
            raise ValueError("over ROS the controller runs the flow policy only (policy: nf); "
                             "train the MLP baseline in process with `train --policy mlp`")
        if self.cfg.task == "block":
            raise ValueError("the block task has no arm; train it in process with `train --task block`")
        if self.settings["on_safe_hold"] not in ON_SAFE_HOLD:
            raise ValueError(f"on_safe_hold must be one of {ON_SAFE_HOLD}, got {self.settings['on_safe_hold']!r}")
        self.chunks = ChunkCollector()
        self.controller_mode: int | None = None  # latest ControllerStatus mode
        self.create_subscription(ControllerStatus, CONTROLLER_STATUS, self._on_status, 10)
        self._clear = self.create_client(Trigger, self.settings["clear_fault_service"])
        self._policy_pub = self.create_publisher(PolicyParametersMsg, POLICY_PARAMETERS, qos.POLICY)
        self.create_subscription(RolloutChunk, ROLLOUTS, self.chunks.add, qos.ROLLOUTS)
        self._action = ActionClient(self, RunEpisode, RUN_EPISODE)
        self.success_depth = 0.016  # m; set from the trainer's scene by RosTraining
        self.spin_lock = SpinLock()  # held by each executor spin slice (ros_runtime.run_node)

    def publish_policy(self, trainer: Trainer) -> int:
        """Publish the trainer's policy (its mean, with parameter exploration) under the version of the
        completed iterations (``policy_version``); returns the version."""
        return self.publish_params(trainer.policy.to_params(), policy_version(trainer))

    def publish_params(self, params: PolicyParameters, version: int) -> int:
        """Publish ``params`` under ``version`` (latched); returns the version."""
        params.version = version
        self._policy_pub.publish(params.fill_msg(PolicyParametersMsg()))
        return version

    def wait_for_policy_subscribers(self, count: int, timeout: float) -> bool:
        """True once ``count`` subscriptions match the policy publisher (within ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        while self._policy_pub.get_subscription_count() < count:
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        return True

    def wait_for_policy_acks(self, timeout: float) -> bool:
        """True once every matched subscriber acknowledged the policies published so far."""
        return self._policy_pub.wait_for_all_acked(Duration(seconds=timeout))

    def _on_status(self, msg: ControllerStatus) -> None:
        self.controller_mode = int(msg.mode)

    def in_safe_hold(self) -> bool:
        """The controller's latest status says safe hold (a latched fault)."""
        return self.controller_mode == ControllerStatus.MODE_SAFE_HOLD

    def clear_fault(self, timeout: float = 10.0) -> str:
        """Call the controller's clear_fault service; its answer, or why there was none."""
        if not self._clear.wait_for_service(timeout_sec=timeout):
            return f"no {self.settings['clear_fault_service']} service"
        with self.spin_lock:
            future = self._clear.call_async(Trigger.Request())
        if not _wait(future, time.monotonic() + timeout):
            return "clear_fault did not answer"
        self.controller_mode = None  # the next status tells
        return future.result().message

    def wait_for_server(self, timeout: float) -> bool:
        """True once the controller's ``run_episode`` action server is up."""
        return self._action.wait_for_server(timeout_sec=timeout)

    def run_episode(self, version: int, start_seed: int | None, noise_seed: int, deterministic: bool,
                    timeout: float) -> EpisodeRecord:
        """One episode through the action; raises ``EpisodeFailedError`` (with the reason) if it is not usable."""
        goal = RunEpisode.Goal(policy_version=version, seed=-1 if start_seed is None else int(start_seed),
                               noise_seed=int(noise_seed), duration=self.cfg.episode_seconds,
                               deterministic=deterministic)
        with self.spin_lock:  # see ros_runtime.run_node: the response must not be handled before the send returns
            sent = self._action.send_goal_async(goal)
        deadline = time.monotonic() + timeout
        if not _wait(sent, deadline):
            raise EpisodeFailedError("the controller did not answer the episode goal")
        handle = sent.result()
        if not handle.accepted:
            raise EpisodeFailedError("the controller rejected the episode goal")
        with self.spin_lock:
            done = handle.get_result_async()
        if not _wait(done, deadline):
            with self.spin_lock:
                handle.cancel_goal_async()
            raise EpisodeFailedError(f"episode not finished within {timeout:.0f} s")
        result = done.result().result
        if not result.completed:
            self.chunks.pop(result.episode_id)
            raise EpisodeFailedError(f"controller: {result.message}")
        # the chunks travel on their own topic: give the last ones a moment
        self.chunks.wait_for(result.episode_id, result.n_chunks, 5.0)
        try:
            return episode_from_chunks(
                self.chunks.pop(result.episode_id), success_depth=self.success_depth,
                final_distance=result.final_distance, torque_norm=result.torque_norm,
                final_success=result.success, start_seed=start_seed)
        except IncompleteEpisodeError as exc:
            raise EpisodeFailedError(f"rollout incomplete: {exc}") from None


def policy_version(trainer: Trainer, rollout: int | None = None) -> int:
    """Version of the policy after ``trainer.iteration`` completed iterations. With parameter
    exploration every rollout runs its own parameters, published under the versions in between
    (iteration x ROLLOUT_VERSIONS + rollout + 1), so versions only ever grow, as the controller
    requires."""
    if trainer.explorer is None:
        return trainer.iteration
    base = trainer.iteration * ROLLOUT_VERSIONS
    return base if rollout is None else base + rollout + 1


def _wait(future: Any, deadline: float) -> bool:
    """Block until the rclpy ``future`` is done (True) or ``deadline`` (monotonic s) passes: woken by
    the future's done callback on the executor thread, not by polling."""
    if future.done():
        return True
    done = threading.Event()
    future.add_done_callback(lambda _: done.set())
    return done.wait(max(0.0, deadline - time.monotonic())) or future.done()


class RosTraining:
    """The training loop over ROS (runs in the main thread while an executor spins the node)."""

    def __init__(self, node: LearnerNode, stop: threading.Event) -> None:
        self.node = node
        self.stop = stop
        self.cfg = node.cfg
        self.out_dir = Path(node.settings["out_dir"])
        self.trainer = Trainer(self.cfg, self.out_dir)
        node.success_depth = self.trainer.runner.env.scene.success_depth
        self.dropped = 0
        checkpoint = self.out_dir / CHECKPOINT
        if checkpoint.exists():
            self.trainer.load_checkpoint(checkpoint)
            LOG.info("resuming from %s after iteration %d", checkpoint, self.trainer.iteration)

    def episode(self, version: int, start: int | None, noise: int, deterministic: bool) -> EpisodeRecord | None:
        """One episode with retries; None when it was dropped (reported). A controller in safe hold
        is waited for (or cleared, ``on_safe_hold: auto``) without using up an attempt."""
        s = self.node.settings
        attempt = clears = 0
        while attempt < 1 + int(s["episode_retries"]):
            if self.stop.is_set():
                return None
            try:
                return self.node.run_episode(version, start, noise, deterministic, s["episode_timeout"])
            except EpisodeFailedError as exc:
                LOG.error("episode (start seed %s, noise seed %s) failed, attempt %d: %s", start, noise,
                          attempt + 1, exc)
                if "safe hold" in str(exc) and clears < AUTO_CLEARS_PER_EPISODE:
                    clears += 1
                    if self.recover_from_safe_hold():
                        continue
                attempt += 1
        self.dropped += 1
        LOG.error("episode dropped after %d attempts (%d dropped so far)", 1 + int(s["episode_retries"]), self.dropped)
        return None

    def recover_from_safe_hold(self) -> bool:
        """After an episode failed on the controller's safe hold: clear it ("auto") or wait until a
        person does ("wait"). False when stopped meanwhile."""
        node = self.node
        if node.settings["on_safe_hold"] == "auto":
            LOG.info("controller in safe hold: clearing it (on_safe_hold: auto): %s", node.clear_fault())
            return True
        LOG.error("controller in safe hold: waiting for a person to check the arm and call %s "
                  "(the iteration goes on afterwards)", node.settings["clear_fault_service"])
        node.controller_mode = None
        next_note = time.monotonic() + 30.0
        while not self.stop.is_set():
            if node.controller_mode is not None and not node.in_safe_hold():
                LOG.info("safe hold cleared: going on")
                return True
            if time.monotonic() > next_note:
                LOG.error("still waiting for %s", node.settings["clear_fault_service"])
                next_note += 30.0
            time.sleep(0.05)
        return False

    def run(self) -> int:
        """Train to ``cfg.iterations``, then evaluate; returns an exit code."""
        cfg, trainer = self.cfg, self.trainer
        self.out_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write(self.out_dir / "config.json", json.dumps(cfg.to_dict(), indent=1))
        version = self.node.publish_policy(trainer)
        settings = self.node.settings
        if not self.node.wait_for_server(settings["server_timeout"]):
            LOG.error("no run_episode action server (is nf_controller running?)")
            return 1
        if not self.node.wait_for_policy_subscribers(settings["policy_subscribers"], settings["server_timeout"]):
            LOG.warning("fewer than %d subscribers of %s after %.0f s: going on (a recorder may miss policies)",
                        settings["policy_subscribers"], POLICY_PARAMETERS, settings["server_timeout"])
        try:
            return self._train(version)
        finally:
            if not self.node.wait_for_policy_acks(settings["policy_ack_timeout"]):
                LOG.warning("not every subscriber of %s acknowledged the last policy within %.0f s",
                            POLICY_PARAMETERS, settings["policy_ack_timeout"])

    def _train(self, version: int) -> int:
        cfg, trainer = self.cfg, self.trainer
        LOG.info("NF-PPO over ROS on %s: iterations %d..%d, %d rollouts each, output %s", cfg.task,
                 trainer.iteration + 1, cfg.iterations, cfg.rollouts_per_iter, self.out_dir)
        if trainer.iteration == 0 and self.node.settings["evaluate_prior"] \
                and not (self.out_dir / PRIOR_EVALUATION_FILE).exists():
            LOG.info("the prior first: deterministic, on the held-out starts of the final evaluation")
            if self.evaluate(version, PRIOR_EVALUATION_FILE, "prior"):
                LOG.error("no episode of the prior's evaluation completed: training goes on without it")
            if self.stop.is_set():
                LOG.info("stopped before iteration 1")
                return 0
        while trainer.iteration < cfg.iterations and not self.stop.is_set():
            t0 = time.perf_counter()
            episodes: list[EpisodeRecord | None] = []
            for i, (start, noise, params) in enumerate(trainer.episode_plan()):
                if params is None:  # action exploration: the policy with noise
                    rec = self.episode(version, trainer.runner.start_seed(start), noise, deterministic=False)
                else:  # parameter exploration: this rollout's own deterministic, stable controller
                    v = self.node.publish_params(params, policy_version(trainer, i))
                    rec = self.episode(v, trainer.runner.start_seed(start), noise, deterministic=True)
                episodes.append(rec)
                LOG.debug("iteration %d episode %d/%d", trainer.iteration + 1, i + 1, cfg.rollouts_per_iter)
            if self.stop.is_set():
                break
            done = [e for e in episodes if e is not None]
            if not done:
                LOG.error("iteration %d: every episode failed; stopping", trainer.iteration + 1)
                return 1
            # parameter exploration pairs rollouts: a dropped one stays in place as None
            row = trainer.update(episodes if trainer.explorer is not None else done, time.perf_counter() - t0)
            row["dropped_episodes"] = float(cfg.rollouts_per_iter - len(done))
            trainer.write_metrics()
            trainer.save_checkpoint(self.out_dir / CHECKPOINT)
            version = self.node.publish_policy(trainer)
            LOG.info("iteration %3d/%d  return %9.1f  success %.2f  final distance %.4f m  sigma %.2f  "
                     "rollouts %.1f s  update %.1f s", trainer.iteration, cfg.iterations, row["return_mean"],
                     row["success_rate"], row["final_distance_mean"], row["sigma"], row["rollout_seconds"],
                     row["update_seconds"])
        if self.stop.is_set():
            LOG.info("stopped after iteration %d (checkpoint in %s)", trainer.iteration, self.out_dir)
            return 0
        return self.evaluate(version)

    def evaluate(self, version: int, file_name: str = EVALUATION_FILE, what: str = "evaluation") -> int:
        """The deterministic controller (policy ``version``) from the held-out starts, over ROS;
        writes ``file_name`` (evaluation.json: after training; evaluation_prior.json: before it)."""
        n = self.cfg.eval_episodes if self.cfg.start != "fixed" else min(self.cfg.eval_episodes, 1)
        recs = []
        for k in range(n):
            start = self.trainer.runner.start_seed(EVAL_SEED_BASE + k)
            rec = self.episode(version, start, 0, deterministic=True)
            if rec is not None:
                recs.append(rec)
        if not recs:
            return 0 if n == 0 else 1
        out: dict[str, Any] = {"episodes": len(recs), "iteration": self.trainer.iteration, "over_ros": True}
        out.update(episode_summary(recs))
        out["per_episode"] = [{"start_seed": r.start_seed, "return": r.episode_return, "success": r.final_success,
                               "final_distance": r.final_distance, "max_depth": float(r.depth.max())} for r in recs]
        _atomic_write(self.out_dir / file_name, json.dumps(out, indent=1, default=_json_float))
        LOG.info("%s (deterministic, %d held-out starts): success %.2f, final distance %.4f m", what,
                 len(recs), out["success_rate"], out["final_distance_mean"])
        return 0


def main(argv: list[str] | None = None) -> int:
    """Console script ``learner``: NF-PPO over ROS 2 until the configured iterations are done."""
    logging.basicConfig(level=logging.INFO, format="[learner] %(message)s", stream=sys.stdout)
    return run_node(LearnerNode, "learner", __doc__.split("\n\n")[0], argv,
                    work=lambda node, stop: RosTraining(node, stop).run(), make_executor=SingleThreadedExecutor,
                    epilog="Settings follow --ros-args, e.g. --ros-args --params-file config/gear.yaml "
                           "-p learner_node:out_dir:=runs/x")


if __name__ == "__main__":
    raise SystemExit(main())
