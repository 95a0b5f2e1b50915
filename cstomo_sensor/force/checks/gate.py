"""The plausibility gate: is a frame's change one that a load on the socket up to ``max_force`` can cause?

A frame whose change from the reference lies far outside what any load in the sensor's rated range
can cause is not a force (all-zero or scaled frames from a failing board, huge values, a bit-flipped
text line). Its :class:`FrameResult` has ``valid=False``, a short ``reason`` and NaN force, angles
and field. The gate works on the change relative to the device's *own* reference,
``g = (V - V_ref) / max(|V_ref|, 0.05 rms(V_ref))`` per used channel, so a device whose rubber is
0.2..5 times as resistive as the model (docs/physics.md#real-devices) is judged alike. A frame is
rejected when any of these holds:

1. ``||g|| > DEVICE_MARGIN * k * max_force + NOISE_NORM_FACTOR * ||n40||``: ``k`` is the largest
   ``||y|| / |F|`` of the estimator's calibration set (simulated socket loads 1..40 N; nearly
   linear in |F|), ``||n40||`` the norm of the per-channel noise of a 40 dB board (docs/physics.md#noise,
   the poorest real board), doubled to cover a single-frame reference.
2. any channel's ``|g_i| > DEVICE_MARGIN * e_i * max_force + CHANNEL_NOISE_SIGMAS * n40_i``: ``e_i``
   is channel i's largest ``|y_i| / |F|`` over the calibration set.
3. the estimated force exceeds ``max_force`` (default 1.5 x the rated 40 N).

``DEVICE_MARGIN`` = 3.5 covers a device at the ends of the real-device ranges (E 0.7 MPa: 1.43 x the strain;
d ln(rho) / d theta -19 instead of -12: 1.58 x; nu 0.43: more compressible) loaded to ``max_force``.
Figures for the cuboid_joint (h = 4 mm model): k = 0.0209 /N, ||n40|| = 0.76, so the bound on
``||g||`` is 5.9 at max_force = 60 N; honest simulation (independent mesh, mismatched electrodes)
of 40 N at any direction at 40 dB with a single-frame reference gives ``||g||`` <= 1.6 and every
channel under 0.84 of its bound *before* the margin; an all-zero frame gives ||g|| = 14.4, a frame
scaled by 10 gives 130.
"""
from __future__ import annotations

import numpy as np

from ...inverse.reconstruction import ReconstructionModel

#: Device spread of the real-device ranges, the poorest board's SNR, the noise allowances of the
#: norm and of one channel (module docstring).
DEVICE_MARGIN = 3.5
GATE_SNR_DB = 40.0
NOISE_NORM_FACTOR = 2.0
CHANNEL_NOISE_SIGMAS = 6.0 * np.sqrt(2.0)  # 6 sigma of the difference of two noisy frames


class PlausibilityGate:
    """The gate of one sensor (module docstring), on the normalised change ``y`` of a frame.

    Built from the estimator's calibration set ``forces`` (n, 3) N and ``y`` (n, n_meas), the model
    (its reference and scale) and ``max_force`` (N). :meth:`follow` sets the device's reference, its
    scale and the mask; :meth:`change_quiet` judges a change, :meth:`force` an estimate.
    """

    def __init__(self, forces: np.ndarray, y: np.ndarray, model: ReconstructionModel, max_force: float) -> None:
        F, Y = np.asarray(forces), np.asarray(y)
        mag = np.linalg.norm(F, axis=1)
        loaded = mag > 0
        per_n = np.abs(Y[loaded]) / mag[loaded, None]
        self.max_force = float(max_force)
        self.k = float(np.max(np.linalg.norm(Y[loaded], axis=1) / mag[loaded]))  # ||y|| per N
        ref = model.model_reference
        noise = model.snr_noise(GATE_SNR_DB)
        self.norm_bound = DEVICE_MARGIN * self.k * self.max_force + NOISE_NORM_FACTOR * float(np.linalg.norm(noise))
        self.channel_bound = DEVICE_MARGIN * per_n.max(axis=0) * self.max_force + CHANNEL_NOISE_SIGMAS * noise
        # no |g_i| exceeds the norm ||g||: a norm within every channel's bound needs no channel test
        self._quiet = (float(np.min(self.channel_bound)) * (1 - 1e-9)) ** 2  # (1 - 1e-9): rounding
        self._w = np.ones(len(ref))  # y -> g: keep * y_scale / (device's reference scale)
        self._g = np.empty(len(ref))
        self._over = np.empty(len(ref), dtype=bool)

    def follow(self, reference: np.ndarray, y_scale: float, keep: np.ndarray) -> None:
        """The change relative to the device's own ``reference`` (volts), normalised by ``y_scale``,
        over the channels ``keep``."""
        scale = np.maximum(np.abs(reference), 0.05 * np.sqrt(np.mean(reference**2)))
        with np.errstate(divide="ignore"):
            w = np.where(scale > 0, y_scale / scale, np.inf)  # an all-zero reference: nothing passes
        self._w = np.where(keep, w, 0.0)

    def change_quiet(self, y: np.ndarray) -> str:
        """'' if the change ``y`` (n_meas,) passes, else why not; for a caller inside
        ``np.errstate(over="ignore", invalid="ignore")`` (huge finite values are rejected here: the
        pipeline's per-frame block)."""
        g = np.multiply(y, self._w, out=self._g)
        g2 = float(g.dot(g))
        if not g2 <= self.norm_bound**2:  # NaN/inf too
            return (f"relative change of norm {np.sqrt(g2):.3g}, beyond {self.norm_bound:.3g} (the largest a "
                    f"load up to max_force {self.max_force:g} N can cause)")
        if g2 <= self._quiet:
            return ""
        np.abs(g, out=g)
        if np.greater(g, self.channel_bound, out=self._over).any():
            i = int(np.argmax(g / self.channel_bound))
            return f"channel {i} changed by {g[i]:.3g} of its reference, beyond {self.channel_bound[i]:.3g}"
        return ""

    def force(self, magnitude: float) -> str:
        """'' if an estimate of ``magnitude`` N passes, else why not."""
        return "" if magnitude <= self.max_force else f"force {magnitude:.4g} N beyond max_force {self.max_force:g} N"
