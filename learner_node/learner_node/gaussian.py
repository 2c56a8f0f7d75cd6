"""The Gaussian part shared by the NF and MLP policies: noise std, distribution, log-probability."""

from __future__ import annotations

import torch
from torch.distributions import Normal


class GaussianForceMixin:
    """For a policy with ``mean_force(x, xdot)``, a trainable ``log_std`` and a ``dtype``."""

    log_std: torch.Tensor
    dtype: torch.dtype

    def std(self) -> torch.Tensor:
        """Standard deviation of the action noise, shape (1,) or (dim,)."""
        return torch.exp(self.log_std)

    def distribution(self, x: torch.Tensor, xdot: torch.Tensor) -> Normal:
        """Gaussian action distribution with mean ``mean_force`` and diagonal std."""
        mean = self.mean_force(x, xdot)
        return Normal(mean, self.std().expand_as(mean))

    def log_prob(self, x: torch.Tensor, xdot: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """Log-density of ``action`` summed over action dimensions; shape (N,) (or scalar if unbatched)."""
        return self.distribution(x, xdot).log_prob(torch.as_tensor(action, dtype=self.dtype)).sum(-1)
