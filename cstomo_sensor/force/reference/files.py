"""The device's own reference: how it compares with the model, and its noise (docs/physics.md#real-devices).

A real device is never the nominal sensor. Its unloaded frame (the tare) is the reference of every
difference, and it also tells two things about the device:

- **scale**: the best global factor ``c = <V_ref, V_model> / <V_model, V_model>`` (a rubber batch's
  resistivity scales every voltage alike) and the relative rms of what that factor does not explain,
  ``||V_ref - c V_model|| / ||c V_model||`` (electrode placement, contact, wiring). The pipeline
  normalises by ``c * v_scale`` so that a global factor cancels exactly. A factor outside
  :data:`SCALE_OK` or an unexplained part above :data:`UNEXPLAINED_WARN` is reported at WARN.
- **noise**: a tare of N >= 2 frames gives the per-channel standard deviation (volts), which the
  estimators use instead of the assumed :data:`DEFAULT_NOISE_DB` (the default for a one-frame tare).

Files: a reference is a frames file (docs/formats.md#reference-and-noise-files); several rows are several unloaded frames (mean and
spread). The node saves a tare as a one-row frames file and its noise beside it (``<tare>.noise.csv``,
one row of volts), read back by :func:`read_reference`. The one row is the mean of N frames: a comment
line ``# reference frames: N`` records N (the reference's own noise is the frame's / sqrt(N), which the
foreign-load statistic counts; :data:`LEGACY_NOISE_FRAMES` for a file saved before the line existed).
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ...errors import ConfigError, FrameError
from ...frames_io import check_frame, read_frames, write_frames
from ...model.geometry import DEFAULT_SNR_DB, noise_std

log = logging.getLogger(__name__)

#: The noise assumed without a measurement (one-frame reference): 60 dB, the default scene (docs/physics.md#noise).
DEFAULT_NOISE_DB = DEFAULT_SNR_DB
#: Global factors of a rubber within docs/physics.md#real-devices that need no comment (beyond: a WARN naming it).
SCALE_OK = (0.5, 2.0)
#: The relative rms of the reference that the global factor does not explain, above which the tare
#: report is a WARN. Measured: 1.8 % for an honestly simulated nominal device (0.2 mm jitter), 4.2 %
#: for scenes/devices/cuboid_joint_device_a.yaml (electrodes up to 0.5 mm off, contact 2 x +-30 %);
#: two drive pairs' rows swapped (a wiring error) give far more (test_device.py).
UNEXPLAINED_WARN = 0.05
#: A measured noise (std / rms of the reference) outside these SNRs is not a noise of a board (docs/physics.md#real-devices:
#: 40..70 dB): a saved noise file outside is refused.
NOISE_DB_RANGE = (10.0, 120.0)
#: The comment of a saved one-row reference that records how many frames it is the mean of.
FRAMES_COMMENT = "reference frames:"
#: A one-row reference saved without that line (before it existed) but with a noise file: the node's
#: comment "mean of N frames" gives N when present; else its noise was measured from >= 2 frames, and 2
#: is the count that assumes the most reference noise (the foreign-load statistic stays at its rate).
LEGACY_NOISE_FRAMES = 2
_RECORDED = (re.compile(r"#\s*" + re.escape(FRAMES_COMMENT) + r"\s*(\S+)\s*$"),
             re.compile(r"#.*\bmean of (\d+) frames\b"))  # the node's own comment before the line existed


@dataclass(frozen=True)
class ScaleReport:
    """The device's reference against the model's prediction (module docstring)."""

    factor: float
    unexplained: float

    @classmethod
    def of(cls, reference: np.ndarray, model_reference: np.ndarray) -> ScaleReport:
        m = np.asarray(model_reference, float)
        r = np.asarray(reference, float)
        c = float(np.dot(r, m) / np.dot(m, m))
        res = float(np.linalg.norm(r - c * m) / max(abs(c) * np.linalg.norm(m), 1e-300))
        return cls(c, res)

    @property
    def warn(self) -> bool:
        return not (SCALE_OK[0] <= self.factor <= SCALE_OK[1]) or not self.unexplained <= UNEXPLAINED_WARN

    @property
    def message(self) -> str:
        """One line: the figures and, when they call for it, what to do."""
        s = f"device reference = {self.factor:.4g} x the model's, {self.unexplained:.2%} unexplained"
        notes = []
        if not SCALE_OK[0] <= self.factor <= SCALE_OK[1]:
            notes.append(f"the rubber is {self.factor:.3g} x as resistive as the model (normalised out; its "
                         "stiffness and sensitivity likely differ too): calibrate on known loads (cstomo calibrate)")
        if not self.unexplained <= UNEXPLAINED_WARN:
            notes.append(f"above {UNEXPLAINED_WARN:.0%}: check the electrode wiring and order, the sensor file and "
                         "the contacts, then tare again unloaded; if it stays, calibrate (cstomo calibrate)")
        return s + ("; " + "; ".join(notes) if notes else "")


def tare_file_name(sensor_name: str, geometry_digest: str, device: str, namespace: str = "") -> str:
    """The default tare file's name in the cache directory, ``tare_<name>-<digest>-<device>.csv``:
    keyed by the whole geometry (its digest) and the board (``device``: its port, or ``topic`` for
    topic input), so two sensor files with one name, or a simulated board and the real one, never
    share a tare. With ``namespace`` (a sensor of a launch's list, tools/launching.py) it leads:
    ``tare_<namespace>-<name>-...``, so two sensors of one robot never share one either."""
    ns, dev = _slug(namespace), _slug(device)
    return "tare_" + (f"{ns}-" if ns else "") + f"{sensor_name}-{geometry_digest[:8]}-{dev[-48:]}.csv"


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")


def reference_of(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(mean (n_meas,), per-channel std (n_meas,) or None for one frame) of unloaded frames."""
    f = np.atleast_2d(np.asarray(frames, float))
    if len(f) < 2:
        return f[0].copy(), None
    return f.mean(axis=0), f.std(axis=0, ddof=1)


def noise_path(reference_path: str | Path) -> Path:
    """Where the noise of a saved one-row reference is kept: ``<name>.noise.csv`` beside it."""
    p = Path(reference_path)
    return p.with_name(p.stem + ".noise.csv")


def check_noise(noise: np.ndarray, reference: np.ndarray, what: str = "noise") -> np.ndarray:
    """``noise`` (n_meas,) volts, finite, >= 0 and within :data:`NOISE_DB_RANGE` of the reference's rms."""
    n = check_frame(noise, len(reference), what)
    if (n < 0).any():
        raise ConfigError.bad_value(what, f"negative std at channel {int(np.argmax(n < 0))}", "std >= 0 volts")
    rms = float(np.sqrt(np.mean(np.asarray(reference, float) ** 2)))
    level = float(np.sqrt(np.mean(n**2)))
    lo, hi = NOISE_DB_RANGE
    if not noise_std(reference, hi) <= level <= noise_std(reference, lo):
        snr = 20 * np.log10(rms / level) if level > 0 else float("inf")
        raise ConfigError.bad_value(what, f"rms {level:.3g} V (SNR {snr:.1f} dB)",
                                    f"a board's noise, SNR within {lo:g}..{hi:g} dB of the reference rms {rms:.3g} V")
    return n


def _recorded_frames(path: str | Path) -> int | None:
    """The frame count a one-row reference file records in its comments (module docstring), or None."""
    with open(path, encoding="utf-8", errors="replace") as f:
        comments = [s.strip() for s in f if s.lstrip().startswith("#")]
    for pattern in _RECORDED:
        for c in comments:
            m = pattern.match(c)
            if m:
                if not m.group(1).isdigit() or int(m.group(1)) < 1:
                    raise FrameError(f"{path}: comment {c!r}: expected '# {FRAMES_COMMENT} N', N >= 1 frames")
                return int(m.group(1))
    return None


def read_reference(path: str | Path, n_meas: int = 208) -> tuple[np.ndarray, np.ndarray | None, int]:
    """(reference, noise or None, frames) of a frames file of unloaded frames: the mean and spread of
    several rows; for one row, the noise of ``<name>.noise.csv`` beside it if present, else None
    (the estimators then assume :data:`DEFAULT_NOISE_DB`). ``frames`` is how many frames the reference
    averages: the rows, or for one row the count its comment records (module docstring); one row
    without it: :data:`LEGACY_NOISE_FRAMES` with a noise file (an older saved tare), else 1."""
    frames = read_frames(path, n_meas)
    ref, noise = reference_of(frames)
    count = len(frames)
    npath = noise_path(path)
    if noise is None and npath.is_file():
        rows = read_frames(npath, n_meas)
        if len(rows) != 1:
            raise FrameError(f"{npath}: {len(rows)} rows, expected one row of per-channel noise (volts)")
        noise = check_noise(rows[0], ref, f"noise file {npath}")
    if count == 1:
        count = _recorded_frames(path) or (LEGACY_NOISE_FRAMES if noise is not None else 1)
    return ref, noise, count


def write_reference(path: str | Path, reference: np.ndarray, noise: np.ndarray | None, comment: str,
                    frames: int) -> None:
    """Save a reference (one row: the mean of ``frames`` frames, recorded in a comment line) and its
    noise beside it (or remove a stale noise file)."""
    if isinstance(frames, bool) or not isinstance(frames, (int, np.integer)) or frames < 1:
        raise ConfigError.bad_value("frames", frames, "the count of frames averaged into the reference (>= 1)")
    npath = noise_path(path)
    if noise is None:
        npath.unlink(missing_ok=True)
    else:
        write_frames(npath, noise, comment=f"per-channel noise (std, volts) of the tare {Path(path).name}")
    write_frames(path, reference, comment=f"{comment}\n{FRAMES_COMMENT} {int(frames)}")


#: The time a saved tare was taken, as force/reference/tare_transaction.py ends its comment (``time.strftime``'s ``%Y-%m-%dT%H:%M:%S%z``).
_SAVED_AT = re.compile(r"(\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d[+-]\d{4})\s*$")


def saved_at(path: str | Path) -> float | None:
    """The time (s since the epoch) a reference file records it was saved (the node's saved tare ends its
    first comment with it, docs/formats.md#reference-and-noise-files), or None when it records none."""
    from datetime import datetime

    with open(path, encoding="utf-8", errors="replace") as f:
        for line in f:
            m = _SAVED_AT.search(line) if line.lstrip().startswith("#") else None
            if m:
                try:
                    return datetime.strptime(m.group(1), "%Y-%m-%dT%H:%M:%S%z").timestamp()
                except ValueError:  # a hand-edited date that is none (month 13): as if it recorded none
                    log.warning("%s: saved at %r is not a date; its file's time is used", path, m.group(1))
                    return None
    return None


def tare_age(path: str | Path, now: float, file_time: bool = True) -> float | None:
    """How old (s) the saved tare ``path`` is at ``now`` (s since the epoch): from the time it records
    (:func:`saved_at`), else (``file_time``) its file's modification time, else None; None too when it
    was saved after ``now`` (it cannot be the tare a restart at ``now`` read). The node's restart
    (:meth:`~cstomo_sensor.frame_path.stream.FrameStream.init_reference`) and ``cstomo replay`` with a tare file take their
    age from here (:meth:`~cstomo_sensor.force.slow_states.drift.DriftTracker.widen`)."""
    t = saved_at(path)
    if t is None and file_time:
        t = Path(path).stat().st_mtime
    return None if t is None or t > now + 1.0 else max(now - t, 0.0)
