"""The disk cache of meshes, models and calibrations: npz entries keyed by a hash of every input.

An entry is written atomically with its key; reading one built for other inputs, or one that cannot
be read, returns None and logs why, so the caller rebuilds it (a stale entry is never used). No pickle.
"""
from __future__ import annotations

import fcntl
import hashlib
import json
import logging
import os
import struct
import tempfile
import zipfile
import zlib
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from .errors import ConfigError

log = logging.getLogger(__name__)


def default_cache_dir() -> Path:
    """``$CSTOMO_CACHE_DIR``, else ``$XDG_CACHE_HOME/cstomo_sensor``, else ``~/.cache/cstomo_sensor``."""
    if os.environ.get("CSTOMO_CACHE_DIR"):
        return Path(os.environ["CSTOMO_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "cstomo_sensor"


def input_hash(inputs: dict) -> str:
    """SHA-256 (24 hex digits) of a JSON-able dict of every input."""
    return hashlib.sha256(json.dumps(inputs, sort_keys=True, default=_jsonable).encode()).hexdigest()[:24]


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    raise TypeError(f"not hashable into a cache key: {type(o)}")


#: What reading a damaged npz can raise: a truncated or empty file (EOFError, BadZipFile), a flipped
#: bit (BadZipFile "Bad CRC-32", zlib.error, a header that no longer parses: ValueError, KeyError,
#: struct.error), or a flag bit that turns an entry "encrypted" (RuntimeError) or "compressed with
#: an unknown method" (NotImplementedError).
UNREADABLE = (OSError, EOFError, ValueError, KeyError, zipfile.BadZipFile, zlib.error, struct.error,
              RuntimeError, NotImplementedError)


_miss_callbacks: list = []


@contextmanager
def on_miss(callback):
    """Call ``callback(path)`` at each cache miss (an entry about to be built) inside the block: a
    command says it computes for a while only when it does (cstomo board-sim)."""
    _miss_callbacks.append(callback)
    try:
        yield
    finally:
        _miss_callbacks.remove(callback)


def cache_load(path: Path, key: str, names: tuple[str, ...] = ()) -> dict[str, np.ndarray] | None:
    """Arrays of a cache entry if it exists and was written for ``key`` and holds every array of
    ``names``; else None (a stale, unreadable or damaged entry, one missing an array, or one holding
    a non-finite float, is logged and ignored, so the caller rebuilds it)."""
    arrays = _load(path, key, names)
    if arrays is None:
        for callback in list(_miss_callbacks):
            callback(path)
    return arrays


def _load(path: Path, key: str, names: tuple[str, ...]) -> dict[str, np.ndarray] | None:
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["cache_key"]) != key:
                log.warning("cache entry %s was built for other inputs: rebuilding", path)
                return None
            arrays = {k: z[k] for k in z.files}
    except UNREADABLE as err:
        log.warning("cache entry %s unreadable (%s: %s): rebuilding", path, type(err).__name__, err)
        return None
    missing = sorted(set(names) - set(arrays))
    if missing:
        log.warning("cache entry %s lacks the arrays %s: rebuilding", path, missing)
        return None
    for k, a in arrays.items():
        if a.dtype.kind in "fc" and not np.isfinite(a).all():
            log.warning("cache entry %s holds %d non-finite values in %r: rebuilding", path,
                        int((~np.isfinite(a)).sum()), k)
            return None
    return arrays


@contextmanager
def build_lock(path: Path):
    """Hold an exclusive lock on the file ``<entry>.lock`` beside the entry ``path`` while the block runs:
    read the entry, and build and save it on a miss, inside the block.

    Why: two processes that miss the same entry at once (the test suite's two workers, two nodes
    started together) would each build it, minutes of a core each for the same bytes; the writes are
    atomic, so that is safe but wasted. With the lock the second process waits, then reads the first's
    entry. The lock is ``fcntl.flock``: the kernel drops it when its holder exits, even killed, so a
    crashed build never blocks another. An entry nested in another's build (a model's mesh) takes its
    own lock; the nesting only goes from an entry to those it is built from, so no two processes wait
    on each other. No lock file can be made (a read-only cache): the block runs without one.
    """
    lock = path.with_name(path.name + ".lock")
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
        f = open(lock, "a")
    except OSError as err:
        log.debug("cache entry %s: no lock file (%s); building unlocked", path, err)
        f = None
    if f is None:
        yield
        return
    with f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("cache entry %s: another process builds it; waiting for it", path)
            fcntl.flock(f, fcntl.LOCK_EX)
        yield  # closing the file releases the lock


def cache_save(path: Path, key: str, **arrays: np.ndarray) -> None:
    """Write arrays atomically (no pickle) with their key."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}.npz")
    np.savez(tmp, cache_key=np.array(key), **arrays)
    os.replace(tmp, path)


CACHE_REMEDY = "set the parameter 'cache_dir' (or $CSTOMO_CACHE_DIR) to a writable directory"


def check_writable(directory: str | os.PathLike, what: str = "cache directory", remedy: str = CACHE_REMEDY) -> Path:
    """``directory``, created if needed, after writing and removing a probe file in it; else a
    :class:`~cstomo_sensor.errors.ConfigError` naming ``what``, the directory, the cause and the
    ``remedy`` (call this before a long build, so an unwritable cache or tare file is reported at
    once, not after minutes of meshing or at the first tare)."""
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=d, prefix=".write_probe"):  # a name of its own: two sensors
            pass  # of one process check the same directory at once
    except OSError as err:
        raise ConfigError(f"{what} {d} is not writable ({err.strerror or err}): {remedy}") from err
    return d
