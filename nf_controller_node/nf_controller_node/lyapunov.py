"""Lyapunov function of the closed loop and a cheap monitor of its value and rate.

For the arm under the flow controller (gravity compensated, no contact)::

    V = 1/2 dphi^T S dphi + k_rot/2 (3 - tr(R_ref^T R)) + 1/2 dq^T M(q) dq,   dphi = phi(x) - phi(x_ref)

and dV/dt = -xdot^T J^T D J xdot - d_rot |w|^2 - joint damping <= 0; under an external force F
acting at a point moving with velocity v, V(t1) - V(t0) <= integral of F.v dt (passivity).
"""

from __future__ import annotations

import math


class LyapunovMonitor:
    """Tracks V every control period: filtered rate dV/dt, the largest single-step rise, rise count.

    ``tolerance`` (J) is the largest per-step increase that counts as integration noise. ``dt`` is
    the sampling period assumed when ``update`` is not told the real time since the last sample.
    Pure Python floats: about a microsecond per update.
    """

    def __init__(self, dt: float = 0.001, tolerance: float = 1e-6, time_constant: float = 0.02) -> None:
        if dt <= 0.0 or tolerance < 0.0 or time_constant <= 0.0:
            raise ValueError("dt and time_constant must be > 0, tolerance >= 0")
        self.dt = dt
        self.tolerance = tolerance
        self.time_constant = time_constant
        self._alpha = dt / (time_constant + dt)
        self.reset()

    def reset(self) -> None:
        """Forget history (call at the start of an episode)."""
        self.value = math.nan
        self.rate = 0.0  # filtered dV/dt, W
        self.max_rise = 0.0  # largest single-step increase seen, J
        self.rises = 0  # steps whose increase exceeded the tolerance
        self.samples = 0

    def update(self, value: float, dt: float | None = None) -> float:
        """Record V; returns the filtered rate. ``dt`` (s): time since the previous sample (the
        constructor's ``dt`` if None); the filter's weight follows it, so irregular sampling gives
        the right dV/dt. Non-finite V counts as a rise."""
        if not math.isfinite(value):
            self.rises += 1
            return self.rate
        if self.samples:
            step = value - self.value
            if dt is None:
                dt, alpha = self.dt, self._alpha
            else:
                alpha = dt / (self.time_constant + dt)
            self.rate += alpha * (step / dt - self.rate)
            if step > self.max_rise:
                self.max_rise = step
            if step > self.tolerance:
                self.rises += 1
        self.value = value
        self.samples += 1
        return self.rate
