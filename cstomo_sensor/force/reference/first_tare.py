"""The first tare of a device, judged after it is taken (issue 35, item 2). No ROS, no serial.

A tare that replaces a reference is judged against it (force/reference/tare_rules.py: a load leaves a socket-shaped change
that a uniform scale does not explain). The first tare of a device (no saved tare, or ``tare_on_start``)
has only the model's predicted frame to compare with, and against it a load held during the tare cannot
be told from the device's own mismatch with the model: measured on honest frames (the table in
docs/node.md#tare, ``python test/first_tare_table.py``), an unloaded device within the real-device ranges
reads as 25-160 N of "load" against the model's reference once its uniform scale, its contacts' and its
gradient's states are fitted out (the rule between two tares, force/reference/tare_rules.py), and a 20 N load moves that
figure by 0.4-21 N; the part of the change along the loads the estimator knows is larger for an unloaded
corner device than for a nominal one under 20 N. No limit refuses a 5-20 N load there without refusing
unloaded devices.

What does tell, once the first tare is taken: the socket carries only forces that push into it
(elevation above 0 deg: ``Fz < 0`` in the wrench frame, docs/physics.md#socket-contact). A tare taken
under a load ``F`` makes the joint's unloading read as ``-F``: a pull out of the socket (``Fz > 0``),
which no load can cause. :class:`FirstTareWatch` follows the frames after a first tare through the
estimator's linear map (the one the drift tracker's rest test uses: linear in the change, so the
unloading reads as ``-F`` exactly, where the ``model`` estimator's fit stays on the pushing loads it was
trained on) and reports a pull of more than :data:`PULL_MIN_N` newtons (or :data:`PULL_SIGMAS` x its
noise, when that is more, and more than :data:`PULL_REL` x the largest push read since the tare) held for
:data:`PULL_FRAMES` frames in a row. The frame stream then drops that
reference (and its file) and tares again on the next frames, as at a start: the joint is at least partly
unloaded then, and a tare that still carried a part of the load is caught the same way when the rest
goes.

It sees the vertical part of the load that was held during the tare, ``|F| sin(elevation)``: 5 N straight
down or at 45 deg, 10-20 N at 15 deg elevation on the nominal device and device_a (device_b, uncalibrated,
reads loads at a third of their size: 10 N down, 20 N at 45 deg; the table: docs/node.md#tare). It sees
it only when the load goes: while the load the first tare was taken under is held, the forces read from it.
"""
from __future__ import annotations

import math

import numpy as np

from ..checks.consistency import change_noise
from ..slow_states.coordinator import force_map

#: A pull out of the socket (N, ``+Fz``) above this, held :data:`PULL_FRAMES` frames in a row, says that the
#: first tare carried a load. After a true tare (honest frames, 60 dB, the corner devices and the nominal
#: one, loads of 2-20 N at elevations 15..90 deg, unloaded between them) the frames read ``Fz`` up to 0.6 N
#: over 10 frames just after an unloading (the creep compensator's error: the simulated rubber does not
#: creep), 1.5 N on device_b with the coarse test model's linear estimator (its drift tracker took part of
#: a 5 N load, which it reads as 0.7 N, for a uniform change): 3 N keeps twice that margin.
PULL_MIN_N = 3.0
#: ... or this many times the per-frame noise of ``Fz`` through the linear map, when larger (a 40 dB board).
PULL_SIGMAS = 5.0
#: ... and above this fraction of the largest push read since the tare: the unloading of a heavy load held
#: long after a true tare leaves a pull that grows with it (the rubber's creep and the compensator's error
#: of it, 4 % per decade of time by default: 15 % of a load held 10 minutes), where the unloading of the
#: tare's own load follows frames that read it as ~0 N.
PULL_REL = 0.5
#: Frames in a row above the limit: a single spike (a knock, a glitch) is not a pull.
PULL_FRAMES = 10


class FirstTareWatch:
    """The frames after a first tare (module docstring): ``force_map`` (3, n_meas) the estimator's linear
    map of a change to a force (N); ``noise`` (n_meas,) the per-channel noise of a change (y units) over
    the channels ``keep``."""

    def __init__(self, force_map: np.ndarray, noise: np.ndarray, keep: np.ndarray) -> None:
        self._w = np.where(keep, np.asarray(force_map, float), 0.0)  # the force of a change
        self.sigma = math.sqrt(float(np.sum((self._w[2] * np.where(keep, noise, 0.0)) ** 2)))  # of Fz
        self.limit = max(PULL_MIN_N, PULL_SIGMAS * self.sigma)
        self.largest = 0.0  # the largest force (N) read since the tare (PULL_REL)
        self.run = 0
        self._sum = 0.0
        self.pull = 0.0  # the mean pull (N) of the run that fired

    @classmethod
    def of(cls, in_use) -> FirstTareWatch | None:
        """The watch of a reference just set by a first tare (``in_use``: the pipeline's ``InUse`` then; None:
        an estimator without a linear map)."""
        est = in_use.estimator
        fmap = force_map(est)
        if fmap is None:
            return None
        return cls(fmap, change_noise(est.noise, in_use.reference_frames), in_use.keep.copy())

    def observe(self, y: np.ndarray) -> bool:
        """The change ``y`` (n_meas,) of a frame after the first tare; True once :data:`PULL_FRAMES` frames
        in a row pulled more than :attr:`limit` and :data:`PULL_REL` x the largest push since the tare
        (their mean pull: :attr:`pull`)."""
        fx, fy, fz = self._w.dot(y).tolist()
        f = math.sqrt(fx * fx + fy * fy + fz * fz)
        if f > self.largest and fz < 0.0:  # a push (a NaN frame changes nothing)
            self.largest = f
        if not fz > max(self.limit, PULL_REL * self.largest):  # NaN too
            self.run, self._sum = 0, 0.0
            return False
        self.run += 1
        self._sum += fz
        self.pull = self._sum / self.run
        return self.run >= PULL_FRAMES

    def message(self, tare_frames: int, tare_file) -> str:
        """What the log and the diagnostics say when the watch fired (once per first tare)."""
        where = f" and its file {tare_file}" if tare_file else ""
        return (f"the first tare was taken under a load: the frames since read a pull of {self.pull:.1f} N out of the "
                f"socket (limit {self.limit:.1f} N, {PULL_FRAMES} frames in a row), which no load on it can cause, "
                "so the joint carried about that much vertically during the tare and has been unloaded since. "
                f"Its reference{where} is dropped and no force is published until a tare on the next "
                f"{tare_frames} frames: keep the joint unloaded and still; a joint that is loaded in the pose "
                "the node starts in: start it unloaded, or call ~/tare_forced once it is unloaded")
