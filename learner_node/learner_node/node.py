"""learner_node: NF-PPO over ROS 2 for one arm or many. Drives episodes through each arm's
``<ns>/run_episode`` action (arms listed in ``arms`` or found on the graph), assembles the streamed
rollouts (``<ns>/rollouts``), runs the trainer's PPO update once per iteration and publishes the new
policy on every arm's ``<ns>/policy_parameters`` (reliable, transient local, version = completed
iterations). An iteration's rollouts go to every free arm at once (``dispatch.WorkQueue``); a rollout
whose arm is lost runs again on another with the same seeds, and the batch is in rollout order, so
identical arms learn what one arm does. ``arms.json`` says which arm ran what and what was lost.

The training settings are the task's parameters file (the ``/**`` and ``learner_node``
sections), exactly what ``train --config`` reads, so an in-process run and a run over ROS with
the same file and seed draw the same starts and noise. ``out_dir`` gets the same metrics,
checkpoint and evaluation files as ``train``, and (``evaluate_prior``) ``evaluation_prior.json``:
the deterministic prior on the same held-out starts before the first iteration, so a run shows
what it learned against where it began. A restarted learner resumes from the checkpoint
and repeats the interrupted iteration with the same seeds. ``init_checkpoint`` starts a new run
from another run's policy (a simulation checkpoint on the robot path) with this run's goal; the
prior's evaluation is then that policy's, and the run folder's own checkpoint, once there, wins.
Episodes that fail or arrive incomplete are reported and retried with the same seeds, then dropped.
"""

from __future__ import annotations

import json
import logging
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import rclpy
from nf_msgs.action import RunEpisode
from nf_msgs.msg import ControllerStatus, RolloutChunk
from nf_msgs.msg import PolicyParameters as PolicyParametersMsg
from rclpy.action import ActionClient, get_action_names_and_types
from rclpy.duration import Duration
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from nf_core import panda_spec, qos
from nf_core.policy_params import PolicyParameters
from nf_core.ros_runtime import SpinLock, run_node
from nf_core.topics import CONTROLLER_STATUS, POLICY_PARAMETERS, ROLLOUTS, RUN_EPISODE

from .config import TrainConfig
from .dispatch import Outcome, WorkQueue
from .rollout import EpisodeRecord, friction_info
from .ros_episodes import ChunkCollector, IncompleteEpisodeError, episode_from_chunks
from .trainer import (
    CHECKPOINT,
    EVAL_SEED_BASE,
    EVALUATION_FILE,
    PRIOR_EVALUATION_FILE,
    Trainer,
    _atomic_write,
    _json_float,
    episode_friction,
    episode_summary,
    prior_origin,
)

LOG = logging.getLogger("learner_node")
ROLLOUT_VERSIONS = 1000  # parameter exploration: policy versions per iteration (one per dispatched rollout)
NODE_PARAMETERS = {  # learner_node's own settings besides TrainConfig's
    "out_dir": "runs/ros",
    # Arm stacks, by namespace ("/": an arm without one): each serves <ns>/run_episode and publishes
    # <ns>/rollouts and <ns>/controller_status; its policies go to <ns>/policy_parameters. Their
    # clients are made at start, so a listed arm that starts later is answered from its first goal.
    "arms": ["/"],
    "discover_arms": True,  # also use every other <ns>/run_episode server that appears, mid-run too
    "arm_timeout": 5.0,  # s without a controller_status before an arm counts as lost (its episode re-queued)
    "episode_timeout": 120.0,  # s of wall time for one episode (lockstep runs at a few x real time)
    "episode_retries": 2,  # an incomplete episode is run again this often (same seeds), then dropped
    "server_timeout": 60.0,  # s to wait for the first arm's action server
    # A controller in safe hold (a latched fault) fails every episode until the fault is cleared.
    # "wait": the arm waits for a person to call <ns>/nf_controller/clear_fault (hardware), the other
    # arms go on; "auto": clear it at once (simulation only: the next reset puts the arm somewhere new).
    "on_safe_hold": "wait",
    "clear_fault_service": "nf_controller/clear_fault",  # under each arm's namespace
    # Subscribers of each arm's policy_parameters to wait for before its first episode (the controller;
    # 2 with a bag recorder, which subscribes only once it sees this publisher: a short run could end
    # before it did, and the bag would hold no policy). Waited for at most server_timeout.
    "policy_subscribers": 1,
    "policy_ack_timeout": 5.0,  # s to wait at the end for every subscriber to acknowledge the last policy
    # Before the first iteration, the deterministic prior on the same eval_episodes held-out starts as
    # the final evaluation (evaluation_prior.json): what the run learned is then shown, not assumed.
    "evaluate_prior": True,
}
ON_SAFE_HOLD = ("wait", "auto")
AUTO_CLEARS_PER_EPISODE = 3  # "auto": an episode that faults this often after clearing is dropped
ARM_SETTLE = 1.0  # s an arm's server is seen before its first goal: Fast DDS drops a reply to an unmatched client
GOAL_ANSWER_TIMEOUT = 30.0  # s for the controller to accept or reject a goal
ARMS_FILE = "arms.json"  # which arm ran which rollout of every batch, what was lost
DISCOVERY_PERIOD = 1.0  # s between looks for new arms while a batch runs
_FIELDS = {f for f in TrainConfig.__dataclass_fields__}


class EpisodeFailedError(RuntimeError):
    """An episode the controller did not complete, or whose rollout did not fully arrive."""


class ArmLostError(EpisodeFailedError):
    """The arm stopped answering mid-episode (killed, disconnected): the episode runs elsewhere."""


def arm_namespace(name: str) -> str:
    """``name`` as a namespace prefix: "" for the root ("/" or ""), else "/a/b" (no trailing slash)."""
    name = name.strip().strip("/")
    return f"/{name}" if name else ""


def under(ns: str, name: str) -> str:
    """The absolute name of ``name`` in namespace ``ns`` (``arm_namespace`` form)."""
    return f"{ns}/{name.lstrip('/')}"


class ArmLink:
    """One arm stack as the learner sees it: its action client, rollout chunks, controller status,
    policy publisher and clear_fault client, all under its namespace."""

    def __init__(self, node: Node, ns: str, clear_fault_service: str) -> None:
        self.ns = ns
        self.name = ns or "/"
        self.chunks = ChunkCollector()
        self.mode: int | None = None  # latest ControllerStatus mode
        self.status_at: float | None = None  # monotonic s of the latest ControllerStatus
        self.ready_since: float | None = None  # monotonic s since the arm is seen alive
        self.worker: threading.Thread | None = None
        self.subscribers_checked = False
        self.clear_service = under(ns, clear_fault_service)
        node.create_subscription(ControllerStatus, under(ns, CONTROLLER_STATUS), self._on_status, 10)
        self.clear_client = node.create_client(Trigger, self.clear_service)
        self.policy_pub = node.create_publisher(PolicyParametersMsg, under(ns, POLICY_PARAMETERS), qos.POLICY)
        node.create_subscription(RolloutChunk, under(ns, ROLLOUTS), self.chunks.add, qos.ROLLOUTS)
        self.action = ActionClient(node, RunEpisode, under(ns, RUN_EPISODE))

    def _on_status(self, msg: ControllerStatus) -> None:
        self.mode = int(msg.mode)
        self.status_at = time.monotonic()

    def in_safe_hold(self) -> bool:
        """The controller's latest status says safe hold (a latched fault)."""
        return self.mode == ControllerStatus.MODE_SAFE_HOLD

    def alive(self, timeout: float) -> bool:
        """Its action server is matched and its status arrived within ``timeout`` s."""
        fresh = self.status_at is not None and time.monotonic() - self.status_at < timeout
        return fresh and self.action.server_is_ready()

    def describe(self) -> str:
        """What the learner sees of this arm, for an error message: its status and its action server."""
        status = "no controller_status yet" if self.status_at is None else \
            f"last controller_status {time.monotonic() - self.status_at:.1f} s ago"
        server = "matched" if self.action.server_is_ready() else "not matched"
        return f"{self.name}: {status}, run_episode server {server}"

    def lost_reason(self, timeout: float) -> str | None:
        """Why the arm counts as gone, or None while it is alive."""
        if self.status_at is None or time.monotonic() - self.status_at >= timeout:
            return f"no controller_status for {timeout:.0f} s"
        if not self.action.server_is_ready():
            return "its run_episode server disappeared"
        return None

    def usable(self, timeout: float) -> bool:
        """Alive for ``ARM_SETTLE`` s: it may get work."""
        now = time.monotonic()
        if not self.alive(timeout):
            self.ready_since = None
            return False
        if self.ready_since is None:
            self.ready_since = now
        return now - self.ready_since >= ARM_SETTLE


class LearnerNode(Node):
    """The ROS side of the learner: one ``ArmLink`` per arm stack (listed or found)."""

    def __init__(self) -> None:
        super().__init__("learner_node", automatically_declare_parameters_from_overrides=True)
        overrides: dict[str, Any] = {}
        for name, param in self._parameters.items():
            if name in _FIELDS:
                overrides[name] = param.value
        self.settings = {k: self.get_parameter_or(k, rclpy.Parameter(k, value=v)).value
                         for k, v in NODE_PARAMETERS.items()}
        self.cfg = TrainConfig.from_sources(None, overrides)
        self.friction = self.cfg.friction_ranges()  # what each episode's sim draws (simulation only)
        if self.cfg.policy != "nf":
            raise ValueError("over ROS the controller runs the flow policy only (policy: nf); "
                             "train the MLP baseline in process with `train --policy mlp`")
        if self.cfg.task == "block":
            raise ValueError("the block task has no arm; train it in process with `train --task block`")
        if self.settings["on_safe_hold"] not in ON_SAFE_HOLD:
            raise ValueError(f"on_safe_hold must be one of {ON_SAFE_HOLD}, got {self.settings['on_safe_hold']!r}")
        arms = self.settings["arms"]
        if isinstance(arms, str):
            arms = [arms]
        self.success_depth = 0.016  # m; set from the trainer's scene by RosTraining
        self.spin_lock = SpinLock()  # held by each executor spin slice (ros_runtime.run_node)
        self.arms: dict[str, ArmLink] = {}
        self.policy: tuple[PolicyParameters, int] | None = None  # the latest policy for every arm, its version
        for ns in arms:
            self.add_arm(arm_namespace(ns))

    def add_arm(self, ns: str) -> ArmLink:
        """The link to the arm in namespace ``ns`` (made once; it gets the current policy)."""
        if ns in self.arms:
            return self.arms[ns]
        with self.spin_lock:  # entities change while no spin slice runs
            arm = ArmLink(self, ns, self.settings["clear_fault_service"])
        self.arms[ns] = arm
        if self.policy is not None:
            self._publish(arm, *self.policy)
        return arm

    def discover_arms(self) -> list[ArmLink]:
        """Links to every ``<ns>/run_episode`` action on the graph not known yet (the new ones)."""
        new = []
        suffix = "/" + RUN_EPISODE
        for name, types in get_action_names_and_types(self):
            if name.endswith(suffix) and "nf_msgs/action/RunEpisode" in types:
                ns = arm_namespace(name[:-len(suffix)])
                if ns not in self.arms:
                    new.append(self.add_arm(ns))
        return new

    def publish_policy(self, trainer: Trainer) -> int:
        """Publish the trainer's policy (its mean, with parameter exploration) to every arm under the
        version of the completed iterations (``policy_version``); returns the version."""
        version = policy_version(trainer)
        self.policy = (trainer.policy.to_params(), version)
        for arm in list(self.arms.values()):
            self._publish(arm, *self.policy)
        return version

    def publish_params(self, arm: ArmLink, params: PolicyParameters, version: int) -> int:
        """Publish ``params`` under ``version`` to ``arm`` only (latched); returns the version."""
        return self._publish(arm, params, version)

    @staticmethod
    def _publish(arm: ArmLink, params: PolicyParameters, version: int) -> int:
        params.version = version
        arm.policy_pub.publish(params.fill_msg(PolicyParametersMsg()))
        return version

    def wait_for_policy_subscribers(self, arm: ArmLink, count: int, timeout: float, stop: threading.Event) -> bool:
        """True once ``count`` subscriptions match ``arm``'s policy publisher (within ``timeout`` s)."""
        deadline = time.monotonic() + timeout
        while arm.policy_pub.get_subscription_count() < count:
            if time.monotonic() > deadline or stop.is_set():
                return False
            time.sleep(0.02)
        return True

    def wait_for_policy_acks(self, timeout: float) -> list[str]:
        """Arms whose policy subscribers did not all acknowledge the policies published so far within
        ``timeout`` s (a lost arm's subscription lingers until DDS expires it)."""
        return [arm.name for arm in list(self.arms.values())
                if not arm.policy_pub.wait_for_all_acked(Duration(seconds=timeout))]

    def clear_fault(self, arm: ArmLink, timeout: float = 10.0) -> str:
        """Call the arm's clear_fault service; its answer, or why there was none."""
        if not arm.clear_client.wait_for_service(timeout_sec=timeout):
            return f"no {arm.clear_service} service"
        with self.spin_lock:
            future = arm.clear_client.call_async(Trigger.Request())
        if not _wait(future, time.monotonic() + timeout):
            return "clear_fault did not answer"
        arm.mode = None  # the next status tells
        return future.result().message

    def run_episode(self, arm: ArmLink, version: int, start_seed: int | None, noise_seed: int,
                    deterministic: bool, timeout: float) -> EpisodeRecord:
        """One episode through ``arm``'s action; raises ``ArmLostError`` if the arm goes away meanwhile,
        ``EpisodeFailedError`` (with the reason) if the episode is not usable."""
        goal = RunEpisode.Goal(policy_version=version, seed=-1 if start_seed is None else int(start_seed),
                               noise_seed=int(noise_seed), duration=self.cfg.episode_seconds,
                               deterministic=deterministic)

        def lost() -> str | None:
            return arm.lost_reason(self.settings["arm_timeout"])

        with self.spin_lock:  # see ros_runtime.run_node: the response must not be handled before the send returns
            sent = arm.action.send_goal_async(goal)
        deadline = time.monotonic() + timeout
        if not _wait(sent, min(deadline, time.monotonic() + GOAL_ANSWER_TIMEOUT), lost):
            raise EpisodeFailedError("the controller did not answer the episode goal")
        handle = sent.result()
        if not handle.accepted:
            raise EpisodeFailedError("the controller rejected the episode goal")
        with self.spin_lock:
            done = handle.get_result_async()
        try:
            finished = _wait(done, deadline, lost)
        except ArmLostError:
            with self.spin_lock:  # if it is only cut off, it stops the episode when the link is back
                handle.cancel_goal_async()
            raise
        if not finished:
            with self.spin_lock:
                handle.cancel_goal_async()
            raise EpisodeFailedError(f"episode not finished within {timeout:.0f} s")
        result = done.result().result
        if not result.completed:
            arm.chunks.pop(result.episode_id)
            raise EpisodeFailedError(f"controller: {result.message}")
        # the chunks travel on their own topic: give the last ones a moment
        arm.chunks.wait_for(result.episode_id, result.n_chunks, 5.0)
        try:
            record = episode_from_chunks(
                arm.chunks.pop(result.episode_id), success_depth=self.success_depth,
                final_distance=result.final_distance, torque_norm=result.torque_norm,
                final_success=result.success, start_seed=start_seed)
        except IncompleteEpisodeError as exc:
            raise EpisodeFailedError(f"rollout incomplete: {exc}") from None
        # the joint friction the sim drew for this start seed (the same function: nf_core.friction)
        record.info.update(friction_info(self.friction, start_seed, len(panda_spec.JOINT_NAMES)))
        return record


def policy_version(trainer: Trainer, dispatch: int | None = None) -> int:
    """Version of the policy after ``trainer.iteration`` completed iterations. With parameter
    exploration every dispatched rollout runs its own parameters, published under the versions in
    between (iteration x ROLLOUT_VERSIONS + dispatch number + 1; a rollout run again gets a new, larger
    one), so versions only ever grow on every arm, as the controller requires."""
    if trainer.explorer is None:
        return trainer.iteration
    base = trainer.iteration * ROLLOUT_VERSIONS
    if dispatch is None:
        return base
    if dispatch + 1 >= ROLLOUT_VERSIONS:
        raise EpisodeFailedError(f"more than {ROLLOUT_VERSIONS - 1} dispatches in one iteration")
    return base + dispatch + 1


def _wait(future: Any, deadline: float, lost: Callable[[], str | None] | None = None) -> bool:
    """Block until the rclpy ``future`` is done (True) or ``deadline`` (monotonic s) passes: woken by
    the future's done callback on the executor thread. With ``lost``, it is asked every 0.1 s and
    ``ArmLostError`` raised with its reason once it gives one."""
    if future.done():
        return True
    done = threading.Event()
    future.add_done_callback(lambda _: done.set())
    while True:
        remaining = deadline - time.monotonic()
        if remaining <= 0.0:
            return future.done()
        if done.wait(remaining if lost is None else min(remaining, 0.1)):
            return True
        if lost is not None and (why := lost()):
            raise ArmLostError(why)


@dataclass
class EpisodeJob:
    """One rollout of a batch: its start and noise seeds, and either its own parameters (parameter
    exploration: published under a fresh version on the arm that runs it) or the policy version to run."""

    start: int | None
    noise: int
    deterministic: bool
    params: PolicyParameters | None = None
    version: int = 0


class RosTraining:
    """The training loop over ROS (runs in the main thread while an executor spins the node); each
    batch of rollouts is spread over the arms by a ``WorkQueue``, one worker thread per arm."""

    def __init__(self, node: LearnerNode, stop: threading.Event) -> None:
        self.node = node
        self.stop = stop
        self.cfg = node.cfg
        self.out_dir = Path(node.settings["out_dir"])
        self.trainer = Trainer(self.cfg, self.out_dir)
        node.success_depth = self.trainer.runner.env.scene.success_depth
        self.dropped = 0
        self._discovered_at = 0.0
        self.arms_log: dict[str, Any] = {"arms": {}, "batches": []}
        resuming = (self.out_dir / CHECKPOINT).exists()
        note = self.trainer.resume_or_init()  # the run folder's own checkpoint, else init_checkpoint
        if note:
            LOG.info("%s", note)
        if resuming and (self.out_dir / ARMS_FILE).exists():
            self.arms_log = json.loads((self.out_dir / ARMS_FILE).read_text())

    # ------------------------------------------------------------------ arms
    def usable_arms(self) -> list[ArmLink]:
        """Arms that may get work now (found ones added first, at most every ``DISCOVERY_PERIOD`` s)."""
        node = self.node
        if node.settings["discover_arms"] and time.monotonic() - self._discovered_at >= DISCOVERY_PERIOD:
            self._discovered_at = time.monotonic()
            for arm in node.discover_arms():
                LOG.info("found arm %s", arm.name)
        return [a for a in list(node.arms.values()) if a.usable(node.settings["arm_timeout"])]

    def run_batch(self, jobs: list[EpisodeJob], what: str) -> WorkQueue[EpisodeRecord]:
        """Run ``jobs`` on every usable arm at once (arms that appear meanwhile join); returns the queue
        (results in job order, what ran where). Ends early, incomplete, when stopped."""
        s = self.node.settings
        queue: WorkQueue[EpisodeRecord] = WorkQueue(len(jobs), retries=int(s["episode_retries"]),
                                                    max_holds=AUTO_CLEARS_PER_EPISODE)
        base = self.trainer.iteration * ROLLOUT_VERSIONS
        next_note = time.monotonic() + 30.0
        while not queue.wait(0.2):
            if self.stop.is_set():
                queue.close()
                break
            usable = self.usable_arms()
            for arm in usable:
                if arm.worker is None or not arm.worker.is_alive():
                    if arm.in_safe_hold() and s["on_safe_hold"] == "wait":
                        continue  # until a person clears it
                    arm.worker = threading.Thread(target=self._worker, args=(arm, queue, jobs, base),
                                                  name=f"arm{arm.ns.replace('/', '_')}", daemon=True)
                    arm.worker.start()
            if time.monotonic() > next_note:
                LOG.warning("%s: %d of %d rollouts not done yet; arms in use: %s", what,
                            len(jobs) - sum(r is not None for r in queue.results()), len(jobs),
                            ", ".join(a.name for a in usable) or "none")
                next_note += 30.0
        self._record(queue, what)
        return queue

    def _worker(self, arm: ArmLink, queue: WorkQueue[EpisodeRecord], jobs: list[EpisodeJob], base: int) -> None:
        """Take rollouts for ``arm`` until the batch is done or the arm is lost or held."""
        node, s = self.node, self.node.settings
        if not arm.subscribers_checked:
            if not node.wait_for_policy_subscribers(arm, int(s["policy_subscribers"]), s["server_timeout"], self.stop):
                LOG.warning("fewer than %d subscribers of %s after %.0f s: going on (a recorder may miss policies)",
                            s["policy_subscribers"], under(arm.ns, POLICY_PARAMETERS), s["server_timeout"])
            arm.subscribers_checked = True
        while not self.stop.is_set():
            if not queue.wait(0.2, for_work=True):
                if arm.lost_reason(s["arm_timeout"]):
                    return
                continue
            ticket = queue.take(arm.name)
            if ticket is None:
                if queue.complete or not queue.has_pending():
                    return
                continue
            job = jobs[ticket.index]
            try:
                version = job.version
                if job.params is not None:
                    version = node.publish_params(arm, job.params, base + ticket.number + 1)
                rec = node.run_episode(arm, version, job.start, job.noise, job.deterministic, s["episode_timeout"])
            except ArmLostError as exc:
                queue.fail(ticket, Outcome.LOST, str(exc))
                arm.ready_since = None
                LOG.error("arm %s lost (%s): rollout %d goes back to the queue (same seeds)", arm.name, exc,
                          ticket.index)
                return
            except EpisodeFailedError as exc:
                hold = "safe hold" in str(exc)
                again = queue.fail(ticket, Outcome.HOLD if hold else Outcome.FAILED, str(exc))
                LOG.error("arm %s: rollout %d (start seed %s, noise seed %s) failed: %s; %s", arm.name,
                          ticket.index, job.start, job.noise, exc, "it goes back to the queue" if again else "dropped")
                if hold and not self.recover_from_safe_hold(arm, queue):
                    return
                continue
            if not queue.finish(ticket, rec):
                LOG.warning("arm %s: rollout %d arrived after it was re-queued: ignored", arm.name, ticket.index)

    def recover_from_safe_hold(self, arm: ArmLink, queue: WorkQueue[Any]) -> bool:
        """After an episode failed on ``arm``'s safe hold: clear it ("auto") or wait until a person
        does ("wait"; the other arms go on). False when stopped or the batch ended meanwhile."""
        node = self.node
        if node.settings["on_safe_hold"] == "auto":
            LOG.info("arm %s in safe hold: clearing it (on_safe_hold: auto): %s", arm.name, node.clear_fault(arm))
            return True
        LOG.error("arm %s: controller in safe hold: waiting for a person to check the arm and call %s "
                  "(the iteration goes on afterwards; other arms go on)", arm.name, arm.clear_service)
        arm.mode = None
        next_note = time.monotonic() + 30.0
        while not self.stop.is_set() and not queue.complete:
            if arm.mode is not None and not arm.in_safe_hold():
                LOG.info("arm %s: safe hold cleared: going on", arm.name)
                return True
            if time.monotonic() > next_note:
                LOG.error("arm %s: still waiting for %s", arm.name, arm.clear_service)
                next_note += 30.0
            time.sleep(0.05)
        return False

    def _record(self, queue: WorkQueue[EpisodeRecord], what: str) -> None:
        """Add the batch to ``arms.json``: the arm each rollout ran on, every dispatch and its outcome."""
        counts = queue.arm_counts()
        for arm, c in counts.items():
            total = self.arms_log["arms"].setdefault(arm, {})
            for k, v in c.items():
                total[k] = total.get(k, 0) + v
        self.arms_log["batches"].append({
            "batch": what, "ran_on": queue.ran_on(), "dropped": queue.dropped,
            "dispatches": [{"rollout": d.ticket.index, "arm": d.ticket.arm,
                            "outcome": d.outcome.value if d.outcome else "in_flight", "reason": d.reason,
                            "late": d.late} for d in queue.dispatches]})
        self.out_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write(self.out_dir / ARMS_FILE, json.dumps(self.arms_log, indent=1))
        per_arm = ", ".join(f"{arm} {c.get('done', 0)}" for arm, c in sorted(counts.items()))
        lost = sum(c.get("lost", 0) for c in counts.values())
        failed = sum(c.get("failed", 0) + c.get("hold", 0) for c in counts.values())
        LOG.info("%s: rollouts per arm: %s%s%s%s", what, per_arm or "none",
                 f"; {lost} lost with their arm (run again)" if lost else "",
                 f"; {failed} failed (run again)" if failed else "",
                 f"; dropped {queue.dropped}" if queue.dropped else "")

    # ------------------------------------------------------------------ the run
    def run(self) -> int:
        """Train to ``cfg.iterations``, then evaluate; returns an exit code."""
        cfg, trainer = self.cfg, self.trainer
        self.out_dir.mkdir(parents=True, exist_ok=True)
        _atomic_write(self.out_dir / "config.json", json.dumps(cfg.to_dict(), indent=1))
        version = self.node.publish_policy(trainer)
        settings = self.node.settings
        started = time.monotonic()
        deadline, next_note = started + settings["server_timeout"], started + 15.0
        while not self.usable_arms():
            if time.monotonic() > next_note:  # what is missing, while it waits
                next_note += 15.0
                LOG.info("waiting for an arm (%.0f of %.0f s): %s", time.monotonic() - started,
                         settings["server_timeout"],
                         "; ".join(a.describe() for a in list(self.node.arms.values())) or "none found")
            if time.monotonic() > deadline or self.stop.is_set():
                LOG.error("no run_episode action server (is nf_controller running? arms: %s%s)",
                          ", ".join(settings["arms"]), ", and any found" if settings["discover_arms"] else "")
                for arm in list(self.node.arms.values()):
                    LOG.error("after %.0f s: %s", settings["server_timeout"], arm.describe())
                return 1
            time.sleep(0.1)
        try:
            return self._train(version)
        finally:
            missing = self.node.wait_for_policy_acks(settings["policy_ack_timeout"])
            if missing:
                LOG.warning("not every subscriber of %s acknowledged the last policy within %.0f s (arms %s)",
                            POLICY_PARAMETERS, settings["policy_ack_timeout"], ", ".join(missing))

    def _train(self, version: int) -> int:
        cfg, trainer = self.cfg, self.trainer
        LOG.info("NF-PPO over ROS on %s: iterations %d..%d, %d rollouts each, output %s", cfg.task,
                 trainer.iteration + 1, cfg.iterations, cfg.rollouts_per_iter, self.out_dir)
        if self.node.friction.enabled:
            LOG.info("%s (the sim nodes read the same ranges from the task file's /** section)",
                     self.node.friction.describe())
        if trainer.iteration == 0 and self.node.settings["evaluate_prior"] \
                and not (self.out_dir / PRIOR_EVALUATION_FILE).exists():
            LOG.info("the prior%s first: deterministic, on the held-out starts of the final evaluation",
                     prior_origin(trainer.started_from))
            if self.evaluate(version, PRIOR_EVALUATION_FILE, "prior"):
                LOG.error("no episode of the prior's evaluation completed: training goes on without it")
            if self.stop.is_set():
                LOG.info("stopped before iteration 1")
                return 0
        while trainer.iteration < cfg.iterations and not self.stop.is_set():
            t0 = time.perf_counter()
            jobs = []
            for start, noise, params in trainer.episode_plan():
                if params is None:  # action exploration: the policy with noise
                    jobs.append(EpisodeJob(trainer.runner.start_seed(start), noise, False, version=version))
                else:  # parameter exploration: this rollout's own deterministic, stable controller
                    jobs.append(EpisodeJob(trainer.runner.start_seed(start), noise, True, params=params))
            queue = self.run_batch(jobs, f"iteration {trainer.iteration + 1}")
            if self.stop.is_set():
                break
            episodes = queue.results()
            done = [e for e in episodes if e is not None]
            self.dropped += len(queue.dropped)
            if not done:
                LOG.error("iteration %d: every episode failed; stopping", trainer.iteration + 1)
                return 1
            # parameter exploration pairs rollouts: a dropped one stays in place as None
            row = trainer.update(episodes if trainer.explorer is not None else done, time.perf_counter() - t0)
            row["dropped_episodes"] = float(cfg.rollouts_per_iter - len(done))
            row["arms_used"] = float(len({a for a in queue.ran_on() if a is not None}))
            row["rerun_episodes"] = float(sum(d.outcome is not Outcome.DONE for d in queue.dispatches))
            trainer.write_metrics()
            trainer.save_checkpoint(self.out_dir / CHECKPOINT)
            version = self.node.publish_policy(trainer)
            if trainer.evaluation_due() and trainer.iteration < cfg.iterations:  # the last: the final one's
                result = self.evaluation(version, f"evaluation after iteration {trainer.iteration}")
                if result is not None:
                    trainer.record_evaluation(result)
                    trainer.write_metrics()
                    trainer.save_checkpoint(self.out_dir / CHECKPOINT)
            LOG.info("iteration %3d/%d  return %9.1f  success %.2f  final distance %.4f m  sigma %.2f  "
                     "rollouts %.1f s  update %.1f s", trainer.iteration, cfg.iterations, row["return_mean"],
                     row["success_rate"], row["final_distance_mean"], row["sigma"], row["rollout_seconds"],
                     row["update_seconds"])
        if self.stop.is_set():
            LOG.info("stopped after iteration %d (checkpoint in %s)", trainer.iteration, self.out_dir)
            return 0
        return self.evaluate(version)

    def evaluate(self, version: int, file_name: str = EVALUATION_FILE, what: str = "evaluation") -> int:
        """The deterministic controller (policy ``version``) from the held-out starts, over ROS on every
        arm; writes ``file_name`` (evaluation.json: after training; evaluation_prior.json: before it).
        0: done (or nothing to evaluate), 1: no episode completed."""
        if self.cfg.eval_starts == 0:
            return 0
        out = self.evaluation(version, what)
        if out is None:
            return 1
        if file_name == EVALUATION_FILE and self.trainer.evaluation_due():
            self.trainer.record_evaluation(out)  # eval_every's of the last iteration
            self.trainer.write_metrics()
        _atomic_write(self.out_dir / file_name, json.dumps(out, indent=1, default=_json_float))
        return 0

    def evaluation(self, version: int, what: str) -> dict[str, Any] | None:
        """Run the held-out evaluation episodes of policy ``version`` over ROS and summarise them (None: no
        episode completed or nothing to evaluate)."""
        n = self.cfg.eval_starts
        if n == 0:
            return None
        jobs = [EpisodeJob(self.trainer.runner.start_seed(EVAL_SEED_BASE + k), 0, True, version=version)
                for k in range(n)]
        queue = self.run_batch(jobs, what)
        recs = [r for r in queue.results() if r is not None]
        if not recs:
            return None
        out: dict[str, Any] = {"episodes": len(recs), "iteration": self.trainer.iteration, "over_ros": True}
        if self.trainer.started_from is not None:
            out["started_from"] = self.trainer.started_from
        out.update(episode_summary(recs))
        out["per_episode"] = [{"start_seed": r.start_seed, "return": r.episode_return, "success": r.final_success,
                               "final_distance": r.final_distance, "max_depth": float(r.depth.max()),
                               **episode_friction(r)} for r in recs]
        LOG.info("%s (deterministic, %d held-out starts): success %.2f, final distance %.4f m", what,
                 len(recs), out["success_rate"], out["final_distance_mean"])
        return out


def _work(node: LearnerNode, stop: threading.Event) -> int:
    """The learner's main thread: the training over ROS; exit code 2 when its start is refused (a
    checkpoint to resume or to start from that does not fit the settings, a missing one)."""
    try:
        training = RosTraining(node, stop)
    except ValueError as exc:
        LOG.error("not starting: %s", exc)
        return 2
    return training.run()


def main(argv: list[str] | None = None) -> int:
    """Console script ``learner``: NF-PPO over ROS 2 until the configured iterations are done."""
    logging.basicConfig(level=logging.INFO, format="[learner] %(message)s", stream=sys.stdout)
    return run_node(LearnerNode, "learner", __doc__.split("\n\n")[0], argv,
                    work=_work, make_executor=SingleThreadedExecutor,
                    epilog="Settings follow --ros-args, e.g. --ros-args --params-file config/gear.yaml "
                           "-p learner_node:out_dir:=runs/x")


if __name__ == "__main__":
    raise SystemExit(main())
