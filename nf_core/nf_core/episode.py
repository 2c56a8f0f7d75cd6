"""ROS-free core of one RL episode: held noise, the per-decision record, the reward, and the
rollout cut into chunks. The one episode core of the project: the controller runs it over ROS
(``ControlLoop``, driven by the sim bridge or the Franka driver), the trainer's in-process rollouts
(``learner_node.rollout``) and the decision-at-a-time view (``learner_node.analysis.decision_env``) run it
in process.

The controller consumes one joint state per millisecond. An episode of K decisions of P
milliseconds uses K*P + 1 states: at state j = kP (k < K) the noise eps_k ~ N(0, sigma^2) is
drawn from ``numpy.random.default_rng(noise_seed)`` (or a generator the caller passes) and held
for P steps, and the decision's (x, xdot, u_mean) are recorded; the state after the period closes
decision k's reward. The last state (j = KP) closes the last decision and ends the episode (it is
answered without noise). A caller that sees the end of a period from the plant itself (the
simulator's true TCP) closes the decision with ``close_period`` instead; the next state's
``record`` then does not close it again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .action_noise import draw_noise, gaussian_log_prob
from .reward import REWARD_TERMS, RewardWeights, reward_terms

MAX_EPISODE_SECONDS = 3600.0  # s, the longest episode a goal may ask for
MAX_TASK_DEPTH = 1.0  # m, |insertion depth| a task status may report (the fixtures are a few cm deep)


def check_goal_duration(duration: float, default: float) -> float:
    """The episode length (s) a RunEpisode goal asks for: 0 means ``default`` (documented meaning);
    ``ValueError`` with the reason for a negative, NaN, infinite or over-an-hour duration."""
    try:
        value = float(duration)
    except (TypeError, ValueError):
        raise ValueError(f"episode duration must be a number of seconds, got {duration!r}") from None
    if not math.isfinite(value) or value < 0.0:
        raise ValueError(f"episode duration must be finite and >= 0 s (0: the default {default} s), got {value}")
    if value > MAX_EPISODE_SECONDS:
        raise ValueError(f"episode duration {value} s is longer than {MAX_EPISODE_SECONDS:.0f} s")
    return float(default) if value == 0.0 else value


def check_task_depth(depth: float) -> float:
    """An insertion depth (m) from a task status message, or ``ValueError`` with the reason when it
    is not finite or beyond ``MAX_TASK_DEPTH``: check it before it goes into a record or a result."""
    try:
        value = float(depth)
    except (TypeError, ValueError):
        raise ValueError(f"task status depth must be a number of metres, got {depth!r}") from None
    if not math.isfinite(value) or abs(value) >= MAX_TASK_DEPTH:
        raise ValueError(f"task status depth {value:.6g} m is not finite or not within +-{MAX_TASK_DEPTH} m")
    return value


@dataclass(frozen=True)
class EpisodeSpec:
    """What one episode runs: length, decision period, noise, goal and reward weights."""

    episode_id: int
    policy_version: int
    duration: float  # s
    decision_period: float  # s
    control_period: float  # s, one joint state per step
    sigma: np.ndarray | None  # (d,) noise std in N; None: deterministic
    noise_seed: int
    x_goal: np.ndarray  # (d,) m, the reward's goal
    weights: RewardWeights = field(default_factory=RewardWeights)
    chunk_decisions: int = 100  # decisions per streamed chunk

    @property
    def steps_per_decision(self) -> int:
        """P, control steps per decision."""
        return max(1, round(self.decision_period / self.control_period))

    @property
    def decisions(self) -> int:
        """K, decisions per episode."""
        return max(1, round(self.duration / self.decision_period))

    def check(self) -> None:
        """Raise ``ValueError`` for values an episode cannot run with."""
        for name in ("duration", "decision_period", "control_period"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive number of seconds, got {value}")
        if self.decision_period < self.control_period:
            raise ValueError(f"decision_period {self.decision_period} s is shorter than the control period")
        if self.duration > MAX_EPISODE_SECONDS:
            raise ValueError(f"duration {self.duration} s is longer than {MAX_EPISODE_SECONDS:.0f} s")
        if self.chunk_decisions < 1:
            raise ValueError(f"chunk_decisions must be >= 1, got {self.chunk_decisions}")
        if self.sigma is not None and not (np.all(np.isfinite(self.sigma)) and np.all(self.sigma > 0.0)):
            raise ValueError(f"noise std must be finite and > 0, got {self.sigma}")
        self.weights.check()


@dataclass
class Chunk:
    """Decisions [start, stop) of an episode, ready for an ``nf_msgs/RolloutChunk``."""

    seq: int
    final: bool
    n_chunks: int  # valid when final
    t: np.ndarray
    x: np.ndarray
    xdot: np.ndarray
    u_mean: np.ndarray
    action: np.ndarray
    log_prob: np.ndarray
    reward: np.ndarray
    terms: np.ndarray  # (n, 4), REWARD_TERMS order
    depth: np.ndarray


class EpisodeRun:
    """State machine of one episode; the control loop calls ``noise`` and ``record`` per state."""

    def __init__(self, spec: EpisodeSpec, rng: np.random.Generator | None = None) -> None:
        """``rng``: the noise generator to draw from instead of ``default_rng(spec.noise_seed)``."""
        spec.check()
        self.spec = spec
        d = spec.x_goal.shape[0]
        self.K, self.P, self.d = spec.decisions, spec.steps_per_decision, d
        K = self.K
        self.x, self.xdot, self.u_mean = np.zeros((K, d)), np.zeros((K, d)), np.zeros((K, d))
        self.eps = np.zeros((K, d))
        self._reward = np.zeros(K)
        self._terms = {n: np.zeros(K) for n in REWARD_TERMS}
        self._x_end, self._xdot_end = np.zeros((K, d)), np.zeros((K, d))  # state closing each decision
        self._scored = 0  # decisions whose reward is computed (in batches, off the per-state path)
        self.depth = np.full(K, np.nan)
        self.steps = 0  # states consumed
        self.closed = 0  # decisions whose reward is known
        self.chunks_sent = 0
        self.next_chunk_closes = min(spec.chunk_decisions, self.K)  # ``closed`` at which a chunk is ready
        self.torque_sum = 0.0
        self._rng = None
        if spec.sigma is not None:
            self._rng = rng if rng is not None else np.random.default_rng(spec.noise_seed)
        self._zero = np.zeros(d)

    @property
    def done(self) -> bool:
        """All K decisions closed."""
        return self.closed >= self.K

    @property
    def t(self) -> float:
        """Time into the episode, s."""
        return self.steps * self.spec.control_period

    def noise(self) -> np.ndarray:
        """The held noise for the state about to be answered (draws at a decision's first step)."""
        j = self.steps
        if j >= self.K * self.P or self._rng is None:
            return self._zero
        k, r = divmod(j, self.P)
        if r == 0:
            self.eps[k] = draw_noise(self._rng, self.spec.sigma)
        return self.eps[k]

    def record(self, x: np.ndarray, xdot: np.ndarray, u_mean: np.ndarray | None, depth: float,
               torque_norm: float) -> None:
        """Account the state just answered: position x (m), velocity xdot, deterministic force
        ``u_mean`` (only needed at a decision's first step), the latest insertion depth (m, NaN if
        unknown) and |tau - g| (Nm) of the command sent."""
        j = self.steps
        k, r = divmod(j, self.P)
        if r == 0 and k > self.closed:  # the state after decision k-1's period (not closed already)
            self._close(k - 1, x, xdot, depth)
        if k < self.K:
            if r == 0:
                self.x[k], self.xdot[k] = x, xdot
                self.u_mean[k] = u_mean
            self.torque_sum += torque_norm
        self.steps += 1

    def close_period(self, x: np.ndarray, xdot: np.ndarray, depth: float) -> None:
        """Close the decision whose period the states recorded so far complete, with the state at
        its end as the plant reports it (position x, velocity xdot, insertion depth): for callers
        that step the world themselves. ``RuntimeError`` when the states so far do not end an open
        period."""
        k, r = divmod(self.steps, self.P)
        if r != 0 or k == 0 or k > self.K or k - 1 < self.closed:
            raise RuntimeError(f"no open decision period ends after {self.steps} states "
                               f"({self.closed} of {self.K} decisions closed, {self.P} states each)")
        self._close(k - 1, x, xdot, depth)

    def _close(self, k: int, x: np.ndarray, xdot: np.ndarray, depth: float) -> None:
        self._x_end[k], self._xdot_end[k] = x, xdot
        self.depth[k] = depth
        self.closed = k + 1

    def _score(self) -> None:
        """Rewards of the decisions closed since the last call, as the in-process rollout computes
        them (one vectorized ``reward_terms``)."""
        lo, hi = self._scored, self.closed
        if hi <= lo:
            return
        s = slice(lo, hi)
        terms = reward_terms(self._x_end[s] - self.spec.x_goal, self._xdot_end[s], self.u_mean[s] + self.eps[s],
                             self.spec.weights)
        for name in REWARD_TERMS:
            self._terms[name][s] = terms[name]
        self._reward[s] = np.sum([terms[n] for n in REWARD_TERMS], axis=0)
        self._scored = hi

    @property
    def reward(self) -> np.ndarray:
        """(K,) reward per decision (valid for the closed ones)."""
        self._score()
        return self._reward

    @property
    def terms(self) -> dict[str, np.ndarray]:
        """REWARD_TERMS -> (K,) the reward's terms per decision (valid for the closed ones)."""
        self._score()
        return self._terms

    def ready_chunks(self) -> list[Chunk]:
        """Chunks whose decisions are all closed and not yet handed out (the last one is final)."""
        out = []
        C = self.spec.chunk_decisions
        n_total = -(-self.K // C)
        while self.chunks_sent < n_total:
            start = self.chunks_sent * C
            stop = min(start + C, self.K)
            if self.closed < stop:
                break
            final = self.chunks_sent == n_total - 1
            out.append(self._chunk(self.chunks_sent, start, stop, final, n_total))
            self.chunks_sent += 1
        # all handed out: never again (closed stops at K)
        self.next_chunk_closes = min(self.chunks_sent * C + C, self.K) if self.chunks_sent < n_total else self.K + 1
        return out

    def _chunk(self, seq: int, start: int, stop: int, final: bool, n_total: int) -> Chunk:
        s = slice(start, stop)
        reward, terms = self.reward, self.terms
        return Chunk(seq=seq, final=final, n_chunks=n_total if final else 0,
                     t=self.decision_times(s), x=self.x[s].copy(),
                     xdot=self.xdot[s].copy(), u_mean=self.u_mean[s].copy(), action=self.action(s),
                     log_prob=self.log_prob(s), reward=reward[s].copy(),
                     terms=np.stack([terms[n][s] for n in REWARD_TERMS], axis=1), depth=self.depth[s].copy())

    def decision_times(self, s: slice = slice(None)) -> np.ndarray:
        """Time of each decision of ``s`` in the episode, s (new array)."""
        return np.arange(self.K)[s] * self.spec.decision_period

    def action(self, s: slice = slice(None)) -> np.ndarray:
        """u_mean + held noise of the decisions ``s`` (new array)."""
        return self.u_mean[s] + self.eps[s]

    def log_prob(self, s: slice = slice(None)) -> np.ndarray:
        """Log-density of the actions of ``s`` under the behaviour policy (zeros when deterministic)."""
        if self.spec.sigma is None:
            return np.zeros(len(self.eps[s]))
        return gaussian_log_prob(self.eps[s], self.spec.sigma)

    @property
    def final_distance(self) -> float:
        """|x - x_goal| at the state that closed the last closed decision, m (NaN before any)."""
        if self.closed == 0:
            return math.nan
        return float(np.linalg.norm(self._x_end[self.closed - 1] - self.spec.x_goal))

    @property
    def episode_return(self) -> float:
        """Sum of the closed decisions' rewards."""
        return float(self.reward[: self.closed].sum())

    @property
    def mean_torque(self) -> float:
        """Mean |tau - g| over the episode's commands, Nm (|tau| when the driver adds g itself)."""
        n = min(self.steps, self.K * self.P)
        return self.torque_sum / n if n else 0.0
