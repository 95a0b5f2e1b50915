"""Running frames through a pipeline, and timing it per frame on one core."""
from __future__ import annotations

import contextlib
import os
import time

import numpy as np


def run_frames(pipe, ref: np.ndarray, frames: np.ndarray, with_field: bool = True, noise: np.ndarray | None = None,
               n_frames: int = 1):
    """(forces, images, residuals, implausible): what the estimator gives on every frame, the
    plausibility gate bypassed (the studies feed inputs beyond the rated range on purpose), and how
    many frames the gate would reject. ``noise``: the tare's per-channel noise (None: 60 dB assumed);
    ``n_frames``: how many frames ``ref`` averages."""
    pipe.set_reference(ref, noise, n_frames)
    out = [pipe.process(f, with_field=with_field, gate=False) for f in frames]
    forces = np.array([r.force for r in out])
    images = np.array([r.field.conductivity_change for r in out]) if with_field else None
    implausible = sum(not pipe.process(f, with_field=False).valid for f in frames)
    return forces, images, np.array([r.residual for r in out]), implausible


@contextlib.contextmanager
def one_core():
    """Run the block pinned to one core of those allowed (where the platform can), then unpin."""
    aff = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    if aff:
        os.sched_setaffinity(0, {min(aff)})
    try:
        yield
    finally:
        if aff:
            os.sched_setaffinity(0, aff)


def time_frames(pipe, frames: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Seconds per ``process(frame, with_field=True)`` and per estimator call, n frames, one core."""
    with one_core():
        idx = np.arange(n) % len(frames)
        for f in frames[:3]:
            pipe.process(f, with_field=True)  # warm-up
        tp = np.empty(n)
        for j, i in enumerate(idx):
            t = time.perf_counter()
            pipe.process(frames[i], with_field=True)
            tp[j] = time.perf_counter() - t
        ys = [pipe.model.normalise(f, pipe.reference) for f in frames]
        for y in ys:
            y[pipe.bad_channels] = 0.0
        te = np.empty(n)
        for j, i in enumerate(idx):
            y = ys[i]
            t = time.perf_counter()
            pipe.estimator.estimate(y)
            te[j] = time.perf_counter() - t
    return tp, te
