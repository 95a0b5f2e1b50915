"""The disk cache of meshes, models and calibrations: npz entries keyed by a hash of every input.

An entry is written atomically with its key; reading one built for other inputs, or one that cannot
be read, returns None and logs why, so the caller rebuilds it (a stale entry is never used). No pickle.
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

import numpy as np

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


def cache_load(path: Path, key: str) -> dict[str, np.ndarray] | None:
    """Arrays of a cache entry if it exists and was written for ``key``; else None (a stale or
    unreadable entry is logged and ignored, so the caller rebuilds it)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["cache_key"]) != key:
                log.warning("cache entry %s was built for other inputs: rebuilding", path)
                return None
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, KeyError) as err:
        log.warning("cache entry %s unreadable (%s): rebuilding", path, err)
        return None


def cache_save(path: Path, key: str, **arrays: np.ndarray) -> None:
    """Write arrays atomically (no pickle) with their key."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + f".tmp{os.getpid()}.npz")
    np.savez(tmp, cache_key=np.array(key), **arrays)
    os.replace(tmp, path)
