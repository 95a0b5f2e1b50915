"""File formats of docs/formats.md: frames, forces and load scripts (CSV)."""
from __future__ import annotations

import contextlib
import io
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from .angles import force_angles_deg
from .errors import ConfigError, FrameError

FORCES_HEADER = "frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg"


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
    finite = np.isfinite(a)
    if finite.all():  # the common case, per frame
        return a
    bad = ~finite if used is None else ~finite & used
    if bad.any():
        raise FrameError(f"{what} holds {int(bad.sum())} NaN/Inf values (first at index {int(np.argmax(bad))}); expected finite volts")
    return a


def _lines(path: str | os.PathLike, err: type[Exception], what: str) -> list[tuple[int, str]]:
    """(line number, stripped text) of the non-blank, non-comment ('#') lines of a UTF-8 CSV file;
    an unreadable, binary or non-UTF-8 file raises ``err`` naming the file (and line)."""
    try:
        raw = Path(path).read_bytes()
    except OSError as e:
        raise err(f"{path}: cannot be read ({e.strerror or e}); expected a {what}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        line = raw[: e.start].count(b"\n") + 1
        raise err(f"{path}:{line}: not UTF-8 text (byte 0x{raw[e.start]:02x}); expected a {what}") from None
    if "\x00" in text:
        line = text[: text.index("\x00")].count("\n") + 1
        raise err(f"{path}:{line}: binary data (a NUL byte); expected a {what}")
    out = []
    for lineno, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if s and not s.startswith("#"):
            out.append((lineno, s))
    return out


def _cell(path, lineno: int, name: str, cell: str, err: type[Exception], empty_ok: bool = False) -> float:
    """One finite number of a CSV cell (NaN for an empty cell where ``empty_ok``)."""
    c = cell.strip()
    if not c and empty_ok:
        return math.nan
    try:
        v = float(c)
    except ValueError:
        raise err(f"{path}:{lineno}: {name}={cell!r}: expected a number") from None
    if not math.isfinite(v):
        raise err(f"{path}:{lineno}: {name}={cell!r}: expected a finite number")
    return v


def read_frames(path: str | os.PathLike, n_meas: int = 208) -> np.ndarray:
    """Read a frames file: (n_frames, n_meas) volts; comment lines start with '#'. A malformed file
    raises :class:`FrameError` naming the file and the line."""
    rows = []
    for lineno, s in _lines(path, FrameError, f"frames file ({n_meas} comma-separated volts a line)"):
        cells = s.split(",")
        if len(cells) != n_meas:
            raise FrameError(f"{path}:{lineno}: {len(cells)} values, expected {n_meas} comma-separated volts")
        rows.append([_cell(path, lineno, f"value {i + 1}", c, FrameError) for i, c in enumerate(cells)])
    if not rows:
        raise FrameError(f"{path}: no frames")
    return np.array(rows, dtype=float)


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike) -> Iterator[io.BufferedWriter]:
    """A binary file that replaces ``path`` only when the block ends without an exception (written
    beside it, then renamed): a failed or interrupted write never leaves a half-written file."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    try:
        try:
            f = open(tmp, "wb")
        except OSError as err:  # named as the user gave it, not by the temporary file's name
            raise OSError(f"{path}: cannot be written ({err.strerror or err})") from err
        with f:
            yield f
            f.flush()
            os.fsync(f.fileno())  # on disk before it replaces the old file (a power cut keeps one of the two)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def check_out_file(path: str | os.PathLike) -> None:
    """Refuse (:class:`ConfigError`) an output file path that cannot be written, before any work: a
    directory, or a file in a directory that does not exist."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"--out {path}: a directory; expected a file path")
    if not p.parent.is_dir():
        raise ConfigError(f"--out {path}: no directory {p.parent}; expected a file in an existing directory")


def write_frames(path: str | os.PathLike, frames: np.ndarray, comment: str | None = None) -> None:
    frames = np.atleast_2d(np.asarray(frames, dtype=float))
    buf = io.StringIO()
    if comment:
        for c in comment.splitlines():
            buf.write(f"# {c}\n")
    np.savetxt(buf, frames, delimiter=",", fmt="%.9e")
    with atomic_write(path) as f:
        f.write(buf.getvalue().encode())


def write_forces(path: str | os.PathLike, forces: np.ndarray, valid: np.ndarray | None = None,
                 consistency: np.ndarray | None = None, foreign_load: np.ndarray | None = None,
                 sigma_n: np.ndarray | None = None, index: np.ndarray | None = None) -> None:
    """Write a forces file from (n, 3) force vectors (newtons, wrench frame).

    ``index`` (int (n,)): the ``frame`` column, each row's frame index in its input (docs/formats.md#forces-file);
    None: 0, 1, 2, ... (one row per input frame).

    ``valid`` (bool (n,)), when given, adds the optional ``valid`` column of the forces file
    (docs/formats.md#forces-file): 1, or 0 for a frame rejected as implausible, whose force fields are left empty.
    ``consistency`` (float (n,)) with ``foreign_load`` (bool (n,)) add the ``consistency`` and
    ``foreign_load`` columns (empty for a frame without a statistic: NaN). ``sigma_n`` (float (n,)) adds
    the ``sigma_n`` column: the force's 1-sigma, the rms of its error's norm (N; empty when NaN).
    """
    f = np.atleast_2d(np.asarray(forces, dtype=float))
    ok = np.ones(len(f), bool) if valid is None else np.asarray(valid, bool)
    if ok.shape != (len(f),):
        raise FrameError(f"valid has shape {ok.shape}, expected ({len(f)},)")
    if (consistency is None) != (foreign_load is None):
        raise FrameError("consistency and foreign_load: give both or neither")
    if consistency is not None:
        cons, flag = np.asarray(consistency, float), np.asarray(foreign_load, bool)
        if cons.shape != (len(f),) or flag.shape != (len(f),):
            raise FrameError(f"consistency/foreign_load shapes {cons.shape}/{flag.shape}, expected ({len(f)},)")
    if sigma_n is not None:
        sig = np.asarray(sigma_n, float)
        if sig.shape != (len(f),):
            raise FrameError(f"sigma_n has shape {sig.shape}, expected ({len(f)},)")
    idx = np.arange(len(f)) if index is None else np.asarray(index, int)
    if idx.shape != (len(f),):
        raise FrameError(f"index has shape {idx.shape}, expected ({len(f)},)")
    mag, el, az = force_angles_deg(np.where(ok[:, None], f, 0.0))
    table = np.column_stack([f, mag, el, az])
    lines = [FORCES_HEADER + (",valid" if valid is not None else "")
             + (",consistency,foreign_load" if consistency is not None else "")
             + (",sigma_n" if sigma_n is not None else "")]
    for i, (row, good) in enumerate(zip(table, ok)):
        fields = ",".join(f"{x:.9g}" for x in row) if good else ",,,,,"
        extra = "" if valid is None else f",{int(good)}"
        if consistency is not None:
            extra += f",{cons[i]:.6g},{int(flag[i])}" if np.isfinite(cons[i]) else ",,"
        if sigma_n is not None:
            extra += f",{sig[i]:.6g}" if good and np.isfinite(sig[i]) else ","
        lines.append(f"{idx[i]},{fields}" + extra)
    with atomic_write(path) as out:
        out.write(("\n".join(lines) + "\n").encode())


def _table(path, err: type[Exception], what: str, required: tuple[str, ...]) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """(column names, [(line number, cells)]) of a CSV file with a header line naming ``required``;
    every row has as many cells as the header."""
    lines = _lines(path, err, what)
    if not lines:
        raise err(f"{path}: empty; expected a {what}")
    lineno, head = lines[0]
    names = [c.strip().lower() for c in head.split(",")]
    missing = [c for c in required if c not in names]
    if missing:
        raise err(f"{path}:{lineno}: header {head[:60]!r} lacks {missing}; the first line must be the header "
                  f"of a {what}")
    rows = []
    for lineno, s in lines[1:]:
        cells = s.split(",")
        if len(cells) != len(names):
            raise err(f"{path}:{lineno}: {len(cells)} columns, expected {len(names)} as in the header")
        rows.append((lineno, cells))
    if not rows:
        raise err(f"{path}: no rows after the header; expected a {what}")
    return names, rows


def read_forces(path: str | os.PathLike, with_valid: bool = False):
    """Read a forces (or truth) file: (n, 3) force vectors. Columns are found by the header's names
    (unknown ones are ignored); a row with ``valid`` 0 may leave its force empty (NaN here). With
    ``with_valid``, also the bool (n,) ``valid`` column (all True when the file has none). A
    malformed file raises :class:`FrameError` naming the file and the line."""
    names, rows = _table(path, FrameError, f"forces file ({FORCES_HEADER})", ("fx", "fy", "fz"))
    cols = [names.index(c) for c in ("fx", "fy", "fz")]
    iv = names.index("valid") if "valid" in names else None
    out, valid = np.empty((len(rows), 3)), np.ones(len(rows), bool)
    for k, (lineno, cells) in enumerate(rows):
        rejected = iv is not None and cells[iv].strip() in ("0", "0.0")
        valid[k] = not rejected
        out[k] = [_cell(path, lineno, names[i], cells[i], FrameError, empty_ok=rejected) for i in cols]
    return (out, valid) if with_valid else out


def read_force_rows(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """(frame numbers (n,) int, forces (n, 3)) of a forces file's rows with a force (``valid`` 0 rows
    are skipped); the ``frame`` column is required, unknown columns are ignored."""
    names, rows = _table(path, FrameError, f"forces file ({FORCES_HEADER})", ("frame", "fx", "fy", "fz"))
    cols = [names.index(c) for c in ("frame", "fx", "fy", "fz")]
    iv = names.index("valid") if "valid" in names else None
    frame, forces = [], []
    for lineno, cells in rows:
        if iv is not None and cells[iv].strip() in ("0", "0.0"):
            continue
        v = [_cell(path, lineno, names[i], cells[i], FrameError) for i in cols]
        if v[0] != int(v[0]) or v[0] < 0:
            raise FrameError(f"{path}:{lineno}: frame={cells[cols[0]]!r}: expected a frame number >= 0")
        frame.append(int(v[0]))
        forces.append(v[1:])
    return np.array(frame, dtype=int), np.array(forces, dtype=float).reshape(-1, 3)


def read_forces_table(path: str | os.PathLike, optional: tuple[str, ...] = ("frame", "time", "sigma_n")
                      ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(forces (n, 3), NaN on a row with ``valid`` 0; {name: (n,) values} of the ``optional`` columns the
    file has, NaN where a cell is empty) of a forces file; the angle columns are not read (the force
    components say it all). A malformed file raises :class:`FrameError` naming the file and the line."""
    names, rows = _table(path, FrameError, f"forces file ({FORCES_HEADER})", ("fx", "fy", "fz"))
    cols = [names.index(c) for c in ("fx", "fy", "fz")]
    iv = names.index("valid") if "valid" in names else None
    extra = {name: names.index(name) for name in optional if name in names}
    forces = np.empty((len(rows), 3))
    columns = {name: np.empty(len(rows)) for name in extra}
    for k, (lineno, cells) in enumerate(rows):
        rejected = iv is not None and cells[iv].strip() in ("0", "0.0")
        forces[k] = [_cell(path, lineno, names[i], cells[i], FrameError, empty_ok=rejected) for i in cols]
        if rejected:
            forces[k] = np.nan
        for name, i in extra.items():
            columns[name][k] = _cell(path, lineno, name, cells[i], FrameError, empty_ok=True)
    return forces, columns


def read_load_script(path: str | os.PathLike, max_force: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """Read a load script ``time,fx,fy,fz`` (header line first): (times (n,), forces (n, 3)); times
    finite and not decreasing, every force's magnitude at most ``max_force`` N. A malformed file
    raises :class:`ConfigError` naming the file and line."""
    names, rows = _table(path, ConfigError, "load script (header time,fx,fy,fz)", ("time", "fx", "fy", "fz"))
    if names != ["time", "fx", "fy", "fz"]:
        raise ConfigError(f"{path}: columns {names}, expected time,fx,fy,fz")
    t = np.array([[_cell(path, lineno, names[i], c, ConfigError) for i, c in enumerate(cells)]
                  for lineno, cells in rows])
    back = np.flatnonzero(np.diff(t[:, 0]) < 0)
    if len(back):
        raise ConfigError(f"{path}:{rows[back[0] + 1][0]}: time {t[back[0] + 1, 0]:g} s: times must not decrease")
    magnitude = np.linalg.norm(t[:, 1:4], axis=1)
    over = np.flatnonzero(magnitude > max_force)
    if len(over):
        i = over[0]
        raise ConfigError(f"{path}:{rows[i][0]}: load {i + 1} (time {t[i, 0]:g} s) is {magnitude[i]:g} N; expected a "
                          f"magnitude of 0..{max_force:g} N")
    return t[:, 0], t[:, 1:4]


def load_index(times: np.ndarray, t: float) -> int:
    """The load script's row in force at time t (each row holds until the next row's time); -1
    before the first row."""
    return int(np.searchsorted(times, t, side="right")) - 1


def force_at(times: np.ndarray, forces: np.ndarray, t: float) -> np.ndarray:
    """The load script's force at time t (zero before the first row)."""
    i = load_index(times, t)
    return forces[i] if i >= 0 else np.zeros(3)
