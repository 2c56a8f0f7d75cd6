"""The learner's action noise as the episode core runs it: a Gaussian force, drawn per decision
and held, and its log-density (PPO's behaviour log-probability). ROS-free, no torch."""

from __future__ import annotations

import math

import numpy as np

_LOG_2PI = math.log(2.0 * math.pi)


def draw_noise(rng: np.random.Generator, sigma: np.ndarray) -> np.ndarray:
    """One decision's noise eps ~ N(0, diag sigma^2), N."""
    return sigma * rng.standard_normal(sigma.shape[-1])


def gaussian_log_prob(noise: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """log N(noise; 0, diag sigma^2) summed over the last axis."""
    z = noise / sigma
    return np.sum(-0.5 * z * z - np.log(sigma) - 0.5 * _LOG_2PI, axis=-1)
