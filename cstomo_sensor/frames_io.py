"""File formats of REFERENCE_SENSOR.md section 6: frames, forces and load scripts (CSV)."""
from __future__ import annotations

import io
import os
from pathlib import Path

import numpy as np

from .angles import force_angles
from .errors import FrameError

FORCES_HEADER = "frame,fx,fy,fz,magnitude,elevation,azimuth"


def check_frame(v: np.ndarray, n_meas: int = 208, what: str = "frame", used: np.ndarray | None = None,
                batch: bool = False) -> np.ndarray:
    """The one frame validator: ``v`` as float64 (n_meas,) volts (with ``batch``, also
    (n_frames, n_meas)), or :class:`FrameError` naming the problem. Values outside ``used`` (a bool
    (n_meas,) mask of the channels in use, default all) may be NaN/Inf: a masked channel carries no data."""
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError) as err:
        raise FrameError(f"{what}: {err}; expected {n_meas} numbers") from None
    if a.ndim not in ((1, 2) if batch else (1,)) or a.shape[-1] != n_meas:
        raise FrameError(f"{what} has shape {a.shape}, expected ({n_meas},) voltages")
    bad = ~np.isfinite(a)
    if used is not None:
        bad &= used
    if bad.any():
        raise FrameError(f"{what} holds {int(bad.sum())} NaN/Inf values (first at index {int(np.argmax(bad))}); expected finite volts")
    return a


def read_frames(path: str | os.PathLike, n_meas: int = 208) -> np.ndarray:
    """Read a frames file: (n_frames, n_meas) volts; comment lines start with '#'."""
    rows = []
    for lineno, line in enumerate(Path(path).read_text().splitlines(), 1):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        try:
            vals = [float(t) for t in s.split(",")]
        except ValueError as err:
            raise FrameError(f"{path}:{lineno}: {err}; expected {n_meas} comma-separated numbers") from None
        rows.append(check_frame(vals, n_meas, f"{path}:{lineno}"))
    if not rows:
        raise FrameError(f"{path}: no frames")
    return np.array(rows)


def write_frames(path: str | os.PathLike, frames: np.ndarray, comment: str | None = None) -> None:
    frames = np.atleast_2d(np.asarray(frames, dtype=float))
    buf = io.StringIO()
    if comment:
        for c in comment.splitlines():
            buf.write(f"# {c}\n")
    np.savetxt(buf, frames, delimiter=",", fmt="%.9e")
    Path(path).write_text(buf.getvalue())


def write_forces(path: str | os.PathLike, forces: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Write a forces file from (n, 3) force vectors (newtons, wrench frame).

    ``valid`` (bool (n,)), when given, adds the optional ``valid`` column of REFERENCE_SENSOR.md
    section 6: 1, or 0 for a frame rejected as implausible, whose force fields are left empty.
    """
    f = np.atleast_2d(np.asarray(forces, dtype=float))
    ok = np.ones(len(f), bool) if valid is None else np.asarray(valid, bool)
    if ok.shape != (len(f),):
        raise FrameError(f"valid has shape {ok.shape}, expected ({len(f)},)")
    mag, el, az = force_angles(np.where(ok[:, None], f, 0.0))
    table = np.column_stack([f, mag, el, az])
    lines = [FORCES_HEADER + (",valid" if valid is not None else "")]
    for i, (row, good) in enumerate(zip(table, ok)):
        fields = ",".join(f"{x:.9g}" for x in row) if good else ",,,,,"
        lines.append(f"{i},{fields}" + ("" if valid is None else f",{int(good)}"))
    Path(path).write_text("\n".join(lines) + "\n")


def read_forces(path: str | os.PathLike, with_valid: bool = False):
    """Read a forces (or truth) file: (n, 3) force vectors, NaN where a field is empty (a frame
    rejected as implausible). Columns are found by name; unknown ones are ignored. With
    ``with_valid``, also the bool (n,) ``valid`` column (all True when the file has none)."""
    lines = [ln for ln in Path(path).read_text().splitlines() if ln.strip()]
    if not lines:
        raise FrameError(f"{path}: empty, expected a header line {FORCES_HEADER!r}")
    names = [n.strip() for n in lines[0].split(",")]
    try:
        cols = [names.index(n) for n in ("fx", "fy", "fz")]
    except ValueError:
        raise FrameError(f"{path}: header {lines[0]!r} lacks fx,fy,fz") from None
    iv = names.index("valid") if "valid" in names else None
    forces, valid = np.full((len(lines) - 1, 3), np.nan), np.ones(len(lines) - 1, bool)
    for k, line in enumerate(lines[1:]):
        t = line.split(",")
        try:
            forces[k] = [float(t[c]) if t[c].strip() else np.nan for c in cols]
            if iv is not None:
                valid[k] = t[iv].strip() not in ("0", "")
        except (IndexError, ValueError) as err:
            raise FrameError(f"{path}:{k + 2}: {err}") from None
    return (forces, valid) if with_valid else forces


def read_load_script(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a load script ``time,fx,fy,fz``: (times (n,), forces (n, 3)); times must increase."""
    t = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if t.shape[1] != 4:
        raise FrameError(f"{path}: {t.shape[1]} columns, expected time,fx,fy,fz")
    if np.any(np.diff(t[:, 0]) < 0):
        raise FrameError(f"{path}: times must not decrease")
    return t[:, 0], t[:, 1:4]


def load_index(times: np.ndarray, t: float) -> int:
    """The load script's row in force at time t (each row holds until the next row's time); -1
    before the first row."""
    return int(np.searchsorted(times, t, side="right")) - 1


def force_at(times: np.ndarray, forces: np.ndarray, t: float) -> np.ndarray:
    """The load script's force at time t (zero before the first row)."""
    i = load_index(times, t)
    return forces[i] if i >= 0 else np.zeros(3)
