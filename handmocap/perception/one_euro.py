"""One Euro filter (Casiez, Roussel & Vogel, CHI 2012): low-pass smoothing whose cut-off
rises with speed, so slow motion is smoothed strongly (no jitter) and fast motion lightly
(little lag).

For each new value x at time t (seconds), elementwise over an array:
    dx  = low-pass of (x - x_prev) / dt, with cut-off d_cutoff            (speed estimate)
    fc  = min_cutoff + beta * |dx|                                         (Hz)
    x^  = x_prev^ + alpha(fc, dt) (x - x_prev^),  alpha = 1 / (1 + 1 / (2 pi fc dt))

Tuning (the paper's recipe): with the hand held still, lower min_cutoff until the jitter
is gone; then move fast and raise beta until the lag is acceptable. min_cutoff is in Hz;
beta in Hz per (unit of x per second), so it depends on the unit of x.
"""
import math

import numpy as np


def _alpha(cutoff_hz, dt):
    tau = 1.0 / (2.0 * math.pi * cutoff_hz)
    return 1.0 / (1.0 + tau / dt)


class OneEuroFilter:
    """Filter for an array value of fixed shape. reset() forgets the past (a lost track)."""

    def __init__(self, min_cutoff=1.0, beta=0.0, d_cutoff=1.0):
        self.min_cutoff, self.beta, self.d_cutoff = float(min_cutoff), float(beta), float(d_cutoff)
        self.reset()

    def reset(self):
        self.x = self.dx = self.t = None

    def __call__(self, x, t):
        """Filtered value of x (array) observed at time t (s). The first call returns x;
        a non-increasing t (a repeated stamp) returns the previous output unchanged."""
        x = np.asarray(x, dtype=np.float64)
        if self.x is None:
            self.x, self.dx, self.t = x.copy(), np.zeros_like(x), t
            return self.x.copy()
        dt = t - self.t
        if dt <= 0:
            return self.x.copy()
        self.dx = self.dx + _alpha(self.d_cutoff, dt) * ((x - self.x) / dt - self.dx)
        cutoff = self.min_cutoff + self.beta * np.abs(self.dx)
        tau = 1.0 / (2.0 * math.pi * cutoff)
        self.x = self.x + (x - self.x) / (1.0 + tau / dt)
        self.t = t
        return self.x.copy()
