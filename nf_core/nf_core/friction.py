"""Joint friction randomized per episode: the ranges, their checks and the draw.

A task file's shared settings (``/**``) ``friction_coulomb: [lo, hi]`` (Nm; N for the block's slide
joints) and ``friction_viscous: [lo, hi]`` (Nm s/rad, added to the arm's own damping) give, for every
episode, one Coulomb friction (MuJoCo ``frictionloss``) and one added viscous damping per joint, each
drawn uniformly from its range. The draw is a pure function of the episode's start seed, from a
random stream of its own (``numpy.random.default_rng([seed, FRICTION_STREAM])``), so the starts
(``default_rng(seed)``) are what they were without it, and an episode run in process (``train``) and
one run by the sim node over ROS (the seed of ``RunEpisode`` reaches its ``~/reset``) get the same
friction: both call ``InsertionEnv.reset(seed)``, which applies ``FrictionRanges.draw``. The held-out
evaluation starts (seeds >= ``EVAL_SEED_BASE``) draw from the same ranges. A reset without a seed
(``seed`` None or < 0: the fixed start) gets the middle of each range.

``[0, 0]`` for both (the default) is off: nothing in the simulated model changes at a reset.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FRICTION_STREAM = 30  # second word of the draw's seed: the friction's own random stream
OFF = (0.0, 0.0)
RANGE_NAMES = ("friction_coulomb", "friction_viscous")


def check_range(name: str, value: object) -> tuple[float, float]:
    """``value`` as a range ``(lo, hi)`` of finite numbers with ``0 <= lo <= hi``; ``ValueError``
    naming ``name`` otherwise (a YAML ``[0.2, 1.2]``, a list or tuple of two numbers)."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise ValueError(f"{name} must be a range [lo, hi] of two numbers, got {value!r}")
    items = list(value)
    if any(isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating))
           for v in items):
        raise ValueError(f"{name} must be a range [lo, hi] of two numbers, got {value!r}")
    lo, hi = float(items[0]), float(items[1])
    if not (math.isfinite(lo) and math.isfinite(hi)):
        raise ValueError(f"{name} must be finite, got [{lo}, {hi}]")
    if lo < 0.0:
        raise ValueError(f"{name} must be >= 0 (friction takes energy out), got [{lo}, {hi}]")
    if lo > hi:
        raise ValueError(f"{name} must have lo <= hi, got [{lo}, {hi}]")
    return lo, hi


@dataclass(frozen=True)
class FrictionRanges:
    """The per-episode friction ranges of a task: Coulomb (Nm) and added viscous (Nm s/rad)."""

    coulomb: tuple[float, float] = OFF
    viscous: tuple[float, float] = OFF

    def __post_init__(self) -> None:
        object.__setattr__(self, "coulomb", check_range("friction_coulomb", self.coulomb))
        object.__setattr__(self, "viscous", check_range("friction_viscous", self.viscous))

    @property
    def enabled(self) -> bool:
        """Whether a reset changes the model (not both ranges [0, 0])."""
        return self.coulomb != OFF or self.viscous != OFF

    @property
    def randomized(self) -> bool:
        """Whether episodes differ (a range with lo < hi), not only one fixed value."""
        return self.coulomb[0] < self.coulomb[1] or self.viscous[0] < self.viscous[1]

    def draw(self, seed: int | None, n_joints: int) -> tuple[np.ndarray, np.ndarray]:
        """(Coulomb, added viscous) per joint for the episode of start seed ``seed``: uniform in the
        ranges from ``default_rng([seed, FRICTION_STREAM])``, Coulomb first; the ranges' middles for
        ``seed`` None or < 0 (the fixed start)."""
        if seed is None or seed < 0:
            return (np.full(n_joints, 0.5 * (self.coulomb[0] + self.coulomb[1])),
                    np.full(n_joints, 0.5 * (self.viscous[0] + self.viscous[1])))
        rng = np.random.default_rng([int(seed), FRICTION_STREAM])
        coulomb = rng.uniform(self.coulomb[0], self.coulomb[1], n_joints)
        viscous = rng.uniform(self.viscous[0], self.viscous[1], n_joints)
        return coulomb, viscous

    def describe(self) -> str:
        """One line for a log."""
        c, v = self.coulomb, self.viscous
        return (f"joint friction per episode: Coulomb uniform in [{c[0]:g}, {c[1]:g}] Nm, viscous "
                f"[{v[0]:g}, {v[1]:g}] Nm s/rad added, per joint, from each episode's start seed")
