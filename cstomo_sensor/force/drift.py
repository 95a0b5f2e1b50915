"""The zero that holds: tracking the device's slow change after its tare (docs/physics.md#device-changes).

After a tare the device keeps changing: the rubber warms (its resistivity rises by 0.2..1.5 % per K,
the same sign everywhere, more on the side nearer the motor), the board's current source drifts. The
mean change and the drive scale every voltage of a frame (nearly) alike, ``V = s (V_ref + dV_load)``:
a change of ``s`` by 1 % reads as 18 N at zero load when the change is normalised by the tare alone.
A gradient of the change across the block reads as a lateral load (10 K with 30 % across: 12 N).
:class:`DriftTracker` estimates ``s`` and the gradient ``g`` (along x, y, z: :func:`gradient_directions`)
over time, and the pipeline removes both: ``y = (V / s - V_ref) / y_scale - g . d``.

What separates these slow changes from a load (one frame alone only in part: the normalised change
of a uniform scaling, ``r = V_ref / y_scale``, has a cosine of 0.4..0.7 with a socket load's):

- **shape at rest**: a frame that ``delta r`` alone explains (the whitened residual of the best
  ``delta`` below :data:`REST_BOUND` per channel, the gradient's current part taken out first) is a
  frame without load; it measures the scale and the gradient with their full directions (a noise
  of about 1e-5 per frame). A lateral load looks like a gradient: it is never taken for rest by one.
- **shape under load**: otherwise only the scale is measured, with the part of ``r`` outside the
  span of the socket loads' changes (the top :data:`LOAD_RANK` directions of the estimator's
  whitened calibration set), its variance inflated :data:`LOAD_INFLATION` times: what a load does is
  not taken for a change of the device. The gradient follows at the next rest.
- **time**: the state is a random walk of :data:`RATE` per square-root second (a joint warming by
  15 K in 30 minutes at 1.5 %/K changes ``s`` by 1.3e-4 per second); a Kalman filter weighs each
  frame's measurement against it. Loads move in tenths of seconds; the device in minutes.

What it cannot separate, said plainly:

- a change that is neither a scaling nor a linear gradient: the contact impedances (a uniform
  resistivity change with the contacts unchanged is a scaling plus a contact change: at 10 % its
  remainder reads 0.2-0.3 N), single electrodes' contacts (20 % drift: 0.13 N), a gradient that is not
  linear. That remainder stays in the change, reads as a small force and raises the consistency
  statistic;
- a load held still below about 1 N (the rest bound) is taken for rest: the part of it along ``r``
  goes into ``s`` (it reads low while held and slightly negative for a moment after it is removed);
- a change faster than :data:`RATE` under a long load (it is followed at the next rest).
"""
from __future__ import annotations

import math

import numpy as np

#: Random walk of the scale, per square-root second.
RATE = 2e-4
#: Random walk of the scale's rate of change (per second), per square-root second: the device warms
#: and cools over minutes (15 K in 30 minutes at 0.8 %/K: a rate of 2e-4/s falling to 1e-5/s), so
#: during a load, when the scale is hardly measured, it goes on changing at the rate of the rests
#: (the warm-up's angle error 2.77 -> 2.43 deg; a rate of the gradient too gains nothing).
ACCEL = 2e-6
#: Seconds between frames without stamps (``cstomo estimate`` without ``--rate``).
DEFAULT_PERIOD = 0.01
#: Bound of a rest frame's whitened residual, per channel in use: the noise gives 1 (its chi-square
#: spread over 208 channels is 0.1); a change beyond the directions' reach (the voltages' noise grows
#: as the scale falls, a device's change is not exactly the model's) takes the rest. A 1 N socket
#: load gives several times the bound.
REST_BOUND = 1.5
#: The tracked change (``|s - 1|``) beyond which a re-tare is advised, and beyond which the tracker
#: is outside what it was validated for (``cstomo bench --drift``: uniform changes up to 10 %).
RETARE_ADVISED = 0.05
VALIDATED = 0.10
#: The rubber's stated resistivity coefficient, per kelvin (docs/physics.md#device-changes: 0.2..1.5 %),
#: to express the tracked change in kelvin.
RESISTIVITY_PER_K = 0.008


def gradient_directions(model) -> np.ndarray:
    """(3, n_meas): the normalised change of a resistivity rising linearly across the block along x,
    y and z, by 1 (relative) per half of the block's extent from its middle, through the model's
    sensitivity (``S`` is per relative conductivity change of its basis voxels: ``-S`` per relative
    resistivity change; ``-S @ 1`` is the uniform scaling's ``r`` to 5e-4)."""
    c = np.asarray(model.basis_centers, float)
    lo, hi = c.min(axis=0), c.max(axis=0)
    xi = (c - 0.5 * (lo + hi)) / np.maximum(0.5 * (hi - lo), 1e-12)
    return -(model.S @ xi).T


class DriftTracker:
    """The device's slow change since its tare (module docstring): the uniform scale ``s`` of its
    voltages and a resistivity gradient across the block (``gradient``: (3,) relative change per half
    extent along x, y, z).

    Parameters
    ----------
    r : (n_meas,) ndarray
        The normalised change of a uniform scaling by 1 + 1 (``V_ref / y_scale``).
    gradients : (k, n_meas) ndarray or None
        :func:`gradient_directions` (None: the scale alone is tracked).
    noise : (n_meas,) ndarray
        Per-channel noise std of a change (y units).
    keep : (n_meas,) bool ndarray
        Channels in use.
    """

    def __init__(self, r: np.ndarray, gradients: np.ndarray | None, noise: np.ndarray, keep: np.ndarray) -> None:
        self._args = (r, gradients, noise, keep)
        w = np.where(keep, 1.0 / np.asarray(noise, float), 0.0)
        D = np.atleast_2d(np.asarray(r, float))
        if gradients is not None:
            D = np.vstack([D, gradients])
        D = D * keep
        Dw = D * w
        self.m = m = len(D)  # measured states: the scale, the gradient; then the scale's rate
        self._D, self._w, self._Dw = D, w, Dw
        self._N = np.zeros((m + 1, m + 1))
        self._N[:m, :m] = Dw @ Dw.T
        self._Dw1 = np.vstack([Dw, np.zeros((1, len(w)))])
        self._rest = REST_BOUND * float(np.count_nonzero(keep))
        self._yw = np.empty_like(w)
        self._eye = np.eye(m + 1)
        self._q = np.array([RATE * RATE] * m + [ACCEL * ACCEL])
        self.scale = 1.0
        self.rate = 0.0  # the scale's relative change per second
        self.gradient = np.zeros(m - 1)
        self.offset = np.zeros_like(w)  # the gradient's change: subtracted from the frame's change
        self.P = np.zeros((m + 1, m + 1))
        self.rest_frames = 0  # frames measured as at rest (all time)
        self._t: float | None = None

    def with_mask(self, keep: np.ndarray) -> DriftTracker:
        """The same tracker (its state kept) over the channels ``keep``."""
        r, gradients, noise, _ = self._args
        return self._carried(DriftTracker(r, gradients, noise, keep))

    def with_noise(self, noise: np.ndarray) -> DriftTracker:
        """The same tracker (its state kept) for a change of per-channel noise ``noise`` (y units)."""
        r, gradients, _, keep = self._args
        return self._carried(DriftTracker(r, gradients, noise, keep))

    def _carried(self, new: DriftTracker) -> DriftTracker:
        """``new`` with this tracker's state."""
        new.scale, new.rate, new.P, new.rest_frames, new._t = self.scale, self.rate, self.P, self.rest_frames, self._t
        new._set_gradient(self.gradient)
        return new

    @property
    def change(self) -> float:
        """The tracked relative change of the voltages since the tare (``s - 1``)."""
        return self.scale - 1.0

    def _set_gradient(self, g: np.ndarray) -> None:
        self.gradient = np.asarray(g, float)
        if self.m > 1:
            np.dot(self.gradient, self._D[1:], out=self.offset)

    def observe(self, y: np.ndarray, t: float | None = None) -> bool:
        """Update the state with the normalised change ``y`` (n_meas,) of a frame at time ``t`` (s; None:
        :data:`DEFAULT_PERIOD` after the previous frame), formed with the current state; returns True
        if the frame was taken as at rest."""
        dt = DEFAULT_PERIOD if t is None or self._t is None else min(max(t - self._t, 0.0), 1.0)
        if t is not None:
            self._t = t
        m = self.m
        P = self.P.copy()  # predicted: the scale moves on at its rate, F P F^T + Q with F = I + dt e_0 e_m^T
        P[0] += dt * P[m]
        P[:, 0] += dt * P[:, m]
        P[np.diag_indices_from(P)] += self._q * dt
        yw = np.multiply(y, self._w, out=self._yw)
        b = self._Dw1 @ yw
        # at rest when the scale alone explains the frame (the gradient's current part is already
        # taken out): a lateral load looks like a gradient and must never be taken for one
        rest = float(yw @ yw) - b[0] * b[0] / self._N[0, 0] < self._rest
        step = self.rate * dt
        if not rest:  # under load nothing is measured: a load's change is not the device's (a lateral
            self.scale *= 1.0 + step  # one looks like a gradient); the scale goes on at its rate
            self.P = P
            return False
        self.rest_frames += 1
        info = self._N  # the information matrix and vector of this frame's measurement of the change
        gain = P @ np.linalg.inv(self._eye + info @ P)  # (P^-1 + info)^-1, without inverting P
        delta = gain @ (b - info[:, 0] * step)  # the innovation: what the predicted step leaves
        if np.isfinite(delta).all():
            # the frame was formed with the scale before this frame's step: the step and the update
            self.scale *= (1.0 + step) * (1.0 + float(delta[0]))
            self.rate += float(delta[m])
            if m > 1:
                self._set_gradient(self.gradient + delta[1:m])
            P = gain
        self.P = 0.5 * (P + P.T)
        return True

    def reset(self) -> None:
        """A new reference (a tare): no change since."""
        self.scale, self.rate, self.P, self._t = 1.0, 0.0, np.zeros((self.m + 1, self.m + 1)), None
        self._set_gradient(np.zeros(self.m - 1))

    @property
    def kelvin_text(self) -> str:
        """The tracked change as a temperature change of the rubber at :data:`RESISTIVITY_PER_K`."""
        kelvin = math.log(self.scale) / math.log1p(RESISTIVITY_PER_K) if self.scale > 0 else math.nan
        return f"{kelvin:+.1f} K at {RESISTIVITY_PER_K:.1%}/K, or a drive drift"

    def status(self) -> tuple[int, str]:
        """(0 OK, 1 WARN; a message) of the tracked change for the diagnostics."""
        c = self.change
        text = f"{c:+.2%} since the tare (about {self.kelvin_text})"
        if abs(c) > VALIDATED:
            return 1, f"device changed {text}: beyond the {VALIDATED:.0%} the zero tracking is validated for; re-tare"
        if abs(c) > RETARE_ADVISED:
            return 0, f"device changed {text}: a re-tare is advised when the joint is free"
        return 0, ""
