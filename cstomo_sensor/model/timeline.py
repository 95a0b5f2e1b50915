"""A device over time (docs/physics.md#device-changes), simulated honestly on a scene's truth.

After its tare (t = 0) the simulated device changes: temperature, drive current, contacts, creep,
under a sequence of socket loads (contact tasks with unannounced rests). :class:`TimelineSpec` is the
description (a scene's ``timeline:`` section, docs/formats.md#timeline, or one of the builders
below); :class:`Timeline` puts it on a :class:`~cstomo_sensor.model.simulate.Truth` and gives frames
at any rate (:meth:`Timeline.frames`) or one at a time for the simulated board (:meth:`Timeline.frame`).

What changes, at time t (s after the tare):

* Temperature: the mean change dT(t) (K, piecewise linear). A cell at x changes by
  dT(t) (1 + g(t) s(x)), where s(x) is the coordinate along ``gradient_axis``, centred on the body's
  volume-weighted mean and scaled to |s| <= 1 over the body (so the body's mean change is dT, and
  the side the axis points to, nearer the motor, warms by up to g more). Resistivity is
  multiplied by 1 + alpha dT_local (alpha = ``resistivity_per_k``, +0.2..+1.5 %/K), on top of the
  material law of the load's compression (the two are taken as separable). The true uniform
  resistivity change reported is the body's mean, alpha dT(t).
* Contact impedance of electrode e: z_e(t) = z_e (1 + beta dT_local(x_e, t)) (1 + c_e(t)), with z_e
  the truth's mismatched impedance, beta = ``contact_per_k`` (-0.5..-1.5 %/K) and c_e the
  electrode's own drift (:class:`ContactDrift`: linear to a seeded or given end value, or a seeded
  random walk, |c_e| <= max).
* Drive current: every voltage of a frame times 1 + d(t) (piecewise linear), applied exactly per
  frame.
* Creep (Boltzmann superposition of log creep of each load step): with the steps (t_k, F_k) of the
  socket force (F_-1 = 0) and w_k(t) = 1 + c log10(max(t - t_k, 0.1) / 0.1) for t >= t_k,
  the effective force is F_eff(t) = sum_k w_k(t) (F_k - F_(k-1)). The weights regroup into
  F_eff(t) = sum_j a_j(t) G_j over the distinct forces G_j held so far, with a_j >= 0 (w decreases
  with t_k). The strain simulated is theta(t) = sum_j a_j(t) theta(G_j), theta(G) the compression
  of force G solved once. The socket's compression is positively homogeneous in the force
  (theta(s G) = s theta(G), s >= 0), so wherever every load held so far points the same way
  (a held load's creep, its recovery after removal, a change of magnitude) this is exactly
  theta(F_eff(t)). After a change of direction it superposes the contact patches of the old and
  the new direction instead of solving the contact of F_eff: the difference is the contact's
  non-linearity acting on the old load's residual creep (a weight a_j <= c log10(elapsed / 0.1),
  a few % of that load's strain).

Cost: a forward solve on the truth mesh takes ~40 ms (3 mm mesh), far too slow per frame at
100 frames/s for 30 minutes. The truth is solved at knots instead: within each interval between
load steps (a segment), at its start and end, at every breakpoint of the piecewise linear
profiles, at log-spaced times after the segment's step (0.1 s, then times ``creep_knot_ratio``)
where creep moves, and at most ``state_step_s`` apart. A frame's noise-free voltages interpolate
linearly in time between the two knots of its segment (never across a load step), times the drive
factor; then white noise at the scene's SNR (:func:`~cstomo_sensor.model.simulate.add_noise`, std
from the tare frame). :meth:`Timeline.interpolation_error` measures the interpolation against
direct solves at knot midpoints. The knots' voltages are cached on disk, keyed by every input.
After ``duration`` the device holds its last state.
"""
from __future__ import annotations

import hashlib
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from ..angles import force_angles_deg, force_from_angles
from ..cache import build_lock, cache_load, cache_save, default_cache_dir, input_hash
from ..errors import ConfigError
from ..frames_io import FORCES_HEADER, atomic_write, read_load_script, write_frames
from ..progress import steps
from ..settings import DEFAULT_SENSOR, MAX_LOAD, TYPICAL_CREEP_PER_DECADE
from . import elasticity
from .geometry import DEFAULT_SNR_DB, load_sensor, noise_std
from .material import CONTACT_PER_K, CREEP_T0, RESISTIVITY_PER_K, conductivity_of_theta
from .simulate import (
    CONTACT_MISMATCH,
    ELECTRODE_JITTER,
    MECHANICS_MESH_SIZE,
    TRUTH_MESH_SIZE,
    Load,
    Scene,
    Truth,
    add_noise,
)

log = logging.getLogger(__name__)

#: Cache entry format of the knots (bump when what a knot holds changes).
KNOTS_FORMAT = 1
#: A scene's ``timeline:`` keys (docs/formats.md#timeline) and those of its ``tasks`` and ``contact_drift``.
TIMELINE_KEYS = ("duration", "rate_hz", "temperature", "resistivity_per_k", "contact_per_k", "gradient",
                 "gradient_axis", "drive", "contact_drift", "creep", "loads", "load_script", "tasks",
                 "state_step_s", "creep_knot_ratio")
TASK_KEYS = ("start", "end", "duration_s", "rest_s", "magnitude", "elevation_deg", "seed")
DRIFT_KEYS = ("kind", "max", "step_s", "over_s", "seed", "values")


# --- the description ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Profile:
    """A quantity piecewise linear in time: (t, value) points, linear between them, held before
    the first point and after the last. A single value is a constant."""

    points: tuple[tuple[float, float], ...] = ((0.0, 0.0),)

    @classmethod
    def parse(cls, key: str, v) -> Profile:
        """A number, or a list of [t, value] pairs with strictly increasing finite times."""
        if isinstance(v, Profile):
            return v
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            pts = ((0.0, float(v)),)
        else:
            try:
                pts = tuple((float(t), float(x)) for t, x in v)
            except (TypeError, ValueError):
                raise ConfigError.bad_value(key, v, "a number or a list of [t, value] pairs") from None
        a = np.array(pts, dtype=float).reshape(-1, 2)
        if not len(a) or not np.isfinite(a).all() or np.any(np.diff(a[:, 0]) <= 0):
            raise ConfigError.bad_value(key, v, "[t, value] pairs, finite, times strictly increasing")
        return cls(pts)

    def __call__(self, t) -> np.ndarray:
        a = np.asarray(self.points)
        return np.interp(t, a[:, 0], a[:, 1])

    @property
    def breaks(self) -> np.ndarray:
        return np.asarray(self.points)[:, 0]

    @property
    def is_zero(self) -> bool:
        return all(x == 0 for _, x in self.points)


ZERO = Profile()


@dataclass(frozen=True)
class ContactDrift:
    """Each electrode's own drift of its contact impedance: z_e times 1 + c_e(t), |c_e| <= ``max``.

    ``kind`` 'linear': c_e rises linearly from 0 at t = 0 to its end value at ``over_s`` (default:
    the timeline's duration) and holds; the end values are ``values`` (one per electrode) or drawn
    uniformly in +-max (seeded). ``kind`` 'walk': a Gaussian random walk with nodes every ``step_s``
    seconds, linear between them, scaled so that its std at the end of the timeline is max / 2,
    clipped to +-max (seeded)."""

    kind: str = "walk"
    max: float = 0.2
    step_s: float = 60.0
    over_s: float | None = None
    seed: int = 0
    values: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.kind not in ("walk", "linear"):
            raise ConfigError.bad_value("contact_drift.kind", self.kind, "'walk' or 'linear'")
        if not 0 <= self.max < 1:
            raise ConfigError.bad_value("contact_drift.max", self.max, "0 <= max < 1 (a fraction)")
        if not self.step_s > 0 or (self.over_s is not None and not self.over_s > 0):
            raise ConfigError("contact_drift.step_s and over_s: expected positive seconds")
        if self.values is not None and (self.kind != "linear" or np.any(np.abs(self.values) >= 1)):
            raise ConfigError.bad_value("contact_drift.values", self.values,
                                        "with kind 'linear', one end value per electrode, each in (-1, 1)")

    def times(self, duration: float) -> np.ndarray:
        """The times of the drift's nodes (it is linear between them)."""
        if self.kind == "linear":
            return np.array([0.0, self.over_s or max(duration, 1e-9)])
        return self.step_s * np.arange(max(1, int(np.ceil(duration / self.step_s))) + 1)

    def nodes(self, duration: float, n_electrodes: int) -> tuple[np.ndarray, np.ndarray]:
        """(times (m,), c (m, n_electrodes)): the drift at its nodes, linear between them."""
        rng = np.random.default_rng([self.seed, 20])
        if self.kind == "linear":
            if self.values is not None:
                end = np.asarray(self.values, dtype=float)
                if end.shape != (n_electrodes,):
                    raise ConfigError(f"contact_drift.values: {end.size} values, expected {n_electrodes}")
            else:
                end = rng.uniform(-self.max, self.max, n_electrodes)
            return self.times(duration), np.vstack([np.zeros(n_electrodes), end])
        t = self.times(duration)
        steps = rng.normal(0.0, self.max / 2 / np.sqrt(len(t) - 1), (len(t) - 1, n_electrodes))
        return t, np.clip(np.vstack([np.zeros(n_electrodes), np.cumsum(steps, axis=0)]), -self.max, self.max)

    @classmethod
    def parse(cls, d) -> ContactDrift | None:
        if d is None or isinstance(d, ContactDrift):
            return d
        _check_keys("timeline.contact_drift", d, DRIFT_KEYS)
        kind = d.get("kind", "linear" if "values" in d else "walk")
        return cls(kind=str(kind), max=float(d.get("max", 0.2)),
                   step_s=float(d.get("step_s", 60.0)),
                   over_s=None if d.get("over_s") is None else float(d["over_s"]), seed=int(d.get("seed", 0)),
                   values=None if d.get("values") is None else tuple(float(x) for x in d["values"]))


@dataclass(frozen=True)
class Tasks:
    """Contact tasks with unannounced rests (seeded): from ``start``, a task holds a socket force
    for U(``duration_s``) seconds, then the joint rests (unloaded) for U(``rest_s``) seconds, until
    ``end`` (default: the duration; a task running past it is cut there). The force's magnitude is
    U(``magnitude``) N, its direction uniform over the part of the sphere pushing into the socket at
    elevations ``elevation_deg`` (uniform in sin(elevation) and in azimuth)."""

    start: float = 5.0
    end: float | None = None
    duration_s: tuple[float, float] = (1.0, 30.0)
    rest_s: tuple[float, float] = (1.0, 30.0)
    magnitude: tuple[float, float] = (5.0, 30.0)
    elevation_deg: tuple[float, float] = (15.0, 90.0)
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("duration_s", "rest_s", "magnitude", "elevation_deg"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi or (name != "rest_s" and not hi > 0):
                raise ConfigError.bad_value(f"tasks.{name}", [lo, hi], "[low, high] with 0 <= low <= high")
        if not (0 < self.elevation_deg[0] and self.elevation_deg[1] <= 90):
            raise ConfigError.bad_value("tasks.elevation_deg", self.elevation_deg, "within (0, 90] deg")
        if not self.magnitude[1] <= MAX_LOAD:
            raise ConfigError.bad_value("tasks.magnitude", list(self.magnitude), f"a range within 0..{MAX_LOAD:g} N")

    def steps(self, duration: float) -> tuple[np.ndarray, np.ndarray]:
        """(times (n,), forces (n, 3)): each task's force at its start, a zero force at its end."""
        rng = np.random.default_rng([self.seed, 21])
        end = min(duration, self.end if self.end is not None else duration)
        t, times, forces = float(self.start), [], []
        s0, s1 = np.sin(np.radians(self.elevation_deg))
        while t < end:
            hold = rng.uniform(*self.duration_s)
            el = np.arcsin(rng.uniform(s0, s1))
            f = force_from_angles(rng.uniform(*self.magnitude), el, rng.uniform(0, 2 * np.pi))
            times += [t, min(t + hold, end)]
            forces += [f, np.zeros(3)]
            t = t + hold + rng.uniform(*self.rest_s)
        return np.array(times, dtype=float), np.array(forces, dtype=float).reshape(-1, 3)

    @classmethod
    def parse(cls, d) -> Tasks | None:
        if d is None or isinstance(d, Tasks):
            return d
        _check_keys("timeline.tasks", d, TASK_KEYS)
        kw = {k: (tuple(float(x) for x in d[k]) if k in ("duration_s", "rest_s", "magnitude", "elevation_deg")
                  else int(d[k]) if k == "seed" else None if d[k] is None else float(d[k])) for k in d}
        return cls(**kw)


def _check_keys(where: str, d, keys: tuple[str, ...]) -> None:
    if not isinstance(d, dict):
        raise ConfigError(f"{where}: expected a mapping of some of {list(keys)}")
    unknown = sorted(str(k) for k in d if k not in keys)
    if unknown:
        raise ConfigError(f"unknown keys {[f'{where}.{k}' for k in unknown]}; expected some of "
                          f"{[f'{where}.{k}' for k in keys]}")


def _force_of(item: dict, where: str) -> np.ndarray:
    if "force" in item:
        f = np.asarray(item["force"], dtype=float)
        if f.shape != (3,) or not np.isfinite(f).all():
            raise ConfigError.bad_value(f"{where}.force", item["force"], "[fx, fy, fz] in N")
        return f
    if "magnitude" in item:
        return force_from_angles(float(item["magnitude"]), np.radians(float(item.get("elevation_deg", 90.0))),
                                 np.radians(float(item.get("azimuth_deg", 0.0))))
    raise ConfigError(f"{where}: expected force: [fx, fy, fz] or magnitude (with elevation_deg, azimuth_deg)")


@dataclass(frozen=True)
class TimelineSpec:
    """What happens to the device after its tare (module docstring; docs/formats.md#timeline).

    Profiles are piecewise linear in seconds: ``temperature`` (K, the mean change), ``gradient``
    (fraction of the mean change, +- along ``gradient_axis``), ``drive`` (d: voltages x (1 + d)).
    ``load_times``/``load_forces`` are steps of the socket force (N, wrench frame), each held until
    the next; ``tasks`` adds seeded contact tasks."""

    duration: float = 10.0
    rate_hz: float = 100.0
    temperature: Profile = ZERO
    resistivity_per_k: float = RESISTIVITY_PER_K
    contact_per_k: float = CONTACT_PER_K
    gradient: Profile = ZERO
    gradient_axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    drive: Profile = ZERO
    contact_drift: ContactDrift | None = None
    creep: float = 0.0
    load_times: tuple[float, ...] = ()
    load_forces: tuple[tuple[float, float, float], ...] = ()
    tasks: Tasks | None = None
    state_step_s: float = 30.0
    creep_knot_ratio: float = 2.0

    def __post_init__(self) -> None:
        if not 0 < self.duration < np.inf:
            raise ConfigError.bad_value("timeline.duration", self.duration, "positive seconds")
        if not self.rate_hz > 0:
            raise ConfigError.bad_value("timeline.rate_hz", self.rate_hz, "frames per second > 0")
        if not 0 <= self.creep < 1:
            raise ConfigError.bad_value("timeline.creep", self.creep, "a fraction per decade, 0 <= c < 1 (2..6 %: 0.02..0.06)")
        if not self.state_step_s > 0 or not self.creep_knot_ratio > 1:
            raise ConfigError("timeline.state_step_s > 0 and timeline.creep_knot_ratio > 1 expected")
        ax = np.asarray(self.gradient_axis, dtype=float)
        if ax.shape != (3,) or not np.linalg.norm(ax) > 0:
            raise ConfigError.bad_value("timeline.gradient_axis", self.gradient_axis, "a non-zero [x, y, z]")
        if any(abs(g) >= 1 for _, g in self.gradient.points):
            raise ConfigError.bad_value("timeline.gradient", self.gradient.points, "fractions with |g| < 1")
        if any(abs(d) >= 0.5 for _, d in self.drive.points):
            raise ConfigError.bad_value("timeline.drive", self.drive.points, "relative changes with |d| < 0.5")
        t = np.asarray(self.load_times, dtype=float)
        if len(t) != len(self.load_forces) or not np.isfinite(t).all() or np.any(t < 0) or np.any(np.diff(t) < 0):
            raise ConfigError("timeline.loads: times must be finite, >= 0 and not decrease, one force each")
        magnitude = np.linalg.norm(np.reshape(self.load_forces, (-1, 3)), axis=1)
        over = np.flatnonzero(~(magnitude <= MAX_LOAD))
        if len(over):
            i = over[0]
            raise ConfigError(f"timeline.loads[{i}] (time {t[i]:g} s) is {magnitude[i]:g} N; expected a magnitude of "
                              f"0..{MAX_LOAD:g} N")

    @classmethod
    def from_dict(cls, d: dict, base: Path | None = None) -> TimelineSpec:
        """From a scene's ``timeline:`` mapping; a relative ``load_script`` is taken from ``base``."""
        _check_keys("timeline", d, TIMELINE_KEYS)
        if sum(k in d for k in ("loads", "load_script", "tasks")) > 1:
            raise ConfigError("timeline: give at most one of loads, load_script, tasks")
        kw: dict = {}
        for k in ("duration", "rate_hz", "resistivity_per_k", "contact_per_k", "creep", "state_step_s",
                  "creep_knot_ratio"):
            if k in d:
                try:
                    kw[k] = float(d[k])
                except (TypeError, ValueError):
                    raise ConfigError.bad_value(f"timeline.{k}", d[k], "a number") from None
        for k in ("temperature", "gradient", "drive"):
            if k in d:
                kw[k] = Profile.parse(f"timeline.{k}", d[k])
        if "gradient_axis" in d:
            try:
                kw["gradient_axis"] = tuple(float(x) for x in d["gradient_axis"])
            except (TypeError, ValueError):
                raise ConfigError.bad_value("timeline.gradient_axis", d["gradient_axis"], "[x, y, z]") from None
        kw["contact_drift"] = ContactDrift.parse(d.get("contact_drift"))
        kw["tasks"] = Tasks.parse(d.get("tasks"))
        if "loads" in d:
            items = d["loads"] or []
            for i, it in enumerate(items):
                if not isinstance(it, dict) or "time" not in it:
                    raise ConfigError(f"timeline.loads[{i}]: expected {{time: s, force: [fx, fy, fz]}} or "
                                      "{time: s, magnitude: N, elevation_deg: D, azimuth_deg: D}")
                _check_keys(f"timeline.loads[{i}]", it, ("time", "force", "magnitude", "elevation_deg", "azimuth_deg"))
                try:
                    float(it["time"])
                except (TypeError, ValueError):
                    raise ConfigError.bad_value(f"timeline.loads[{i}].time", it["time"], "seconds, a number") from None
            kw["load_times"] = tuple(float(it["time"]) for it in items)
            kw["load_forces"] = tuple(tuple(_force_of(it, f"timeline.loads[{i}]")) for i, it in enumerate(items))
        if "load_script" in d:
            p = Path(d["load_script"])
            times, forces = read_load_script(p if p.is_absolute() or base is None else base / p, MAX_LOAD)
            kw["load_times"], kw["load_forces"] = tuple(times), tuple(map(tuple, forces))
        return cls(**kw)

    def steps(self) -> tuple[np.ndarray, np.ndarray]:
        """(times (n,), forces (n, 3)) of the socket force's steps within [0, duration): explicit
        loads or the tasks; a step repeating the force before it, or followed by one at the same
        time, is left out."""
        if self.tasks is not None:
            t, f = self.tasks.steps(self.duration)
        else:
            t = np.asarray(self.load_times, dtype=float)
            f = np.asarray(self.load_forces, dtype=float).reshape(-1, 3)
        keep = t < self.duration
        t, f = t[keep], f[keep]
        keep = np.append(np.diff(t) > 0, True)[: len(t)]  # the last of several at one time wins
        t, f = t[keep], f[keep]
        prev = np.vstack([np.zeros((1, 3)), f[:-1]])
        keep = np.any(f != prev, axis=1)
        return t[keep], f[keep]

    def force(self, t) -> np.ndarray:
        """(n, 3) applied socket force at times t (zero before the first step)."""
        st, sf = self.steps()
        n = np.searchsorted(st, np.atleast_1d(t), side="right")
        return np.vstack([np.zeros((1, 3)), sf])[n]

    def creep_weights(self, t, n_steps=None) -> np.ndarray:
        """(len(t), n) w_k(t) = 1 + c log10(max(t - t_k, 0.1) / 0.1) of each step k in force at t
        (those with t_k <= t, or the first ``n_steps`` of them when given), else 0."""
        st, _ = self.steps()
        t = np.atleast_1d(np.asarray(t, dtype=float))
        n = np.searchsorted(st, t, side="right") if n_steps is None else np.broadcast_to(n_steps, t.shape)
        dt = t[:, None] - st[None, :]
        w = 1.0 + self.creep * np.log10(np.maximum(dt, CREEP_T0) / CREEP_T0)
        return np.where(np.arange(len(st))[None, :] < n[:, None], w, 0.0)

    def force_eff(self, t, n_steps=None) -> np.ndarray:
        """(len(t), 3) F_eff(t) = sum_k w_k(t) (F_k - F_(k-1)) (module docstring)."""
        st, sf = self.steps()
        t = np.atleast_1d(np.asarray(t, dtype=float))
        n = np.searchsorted(st, t, side="right") if n_steps is None else np.broadcast_to(n_steps, t.shape)
        dF = np.diff(np.vstack([np.zeros((1, 3)), sf]), axis=0)
        out = np.zeros((len(t), 3))
        for k in range(len(st)):  # one step at a time: (n_frames, n_steps) would not fit for long runs
            on = k < n
            w = 1.0 + self.creep * np.log10(np.maximum(t[on] - st[k], CREEP_T0) / CREEP_T0)
            out[on] += w[:, None] * dF[k]
        return out

    def knots(self) -> tuple[np.ndarray, np.ndarray]:
        """(times (m,), steps in force (m,)) where the truth is solved (module docstring), sorted
        by segment then time; every segment [t_n, t_(n+1)) has a knot at both ends."""
        st, sf = self.steps()
        ends = np.concatenate([[0.0], st, [self.duration]])
        breaks = [self.temperature.breaks, self.gradient.breaks, st + CREEP_T0]
        if self.contact_drift is not None:
            breaks.append(self.contact_drift.times(self.duration))
        breaks = np.unique(np.concatenate(breaks))
        T, N = [], []
        for n in range(len(st) + 1):
            a, b = ends[n], ends[n + 1]
            if b <= a:
                continue
            k = [a, b, *breaks[(breaks > a + 1e-9) & (breaks < b - 1e-9)]]
            if self.creep > 0 and n > 0:
                off = CREEP_T0 * self.creep_knot_ratio ** np.arange(int(np.log(max(b - a, CREEP_T0) / CREEP_T0)
                                                                         / np.log(self.creep_knot_ratio)) + 1)
                k += list(a + off[off < b - a - 1e-9])
            k = np.unique(k)
            k = k[np.append(True, np.diff(k) > 1e-9)]  # a first, b last, nothing within 1 ns
            gaps = np.diff(k)
            fill = [np.linspace(k[i], k[i + 1], int(np.ceil(g / self.state_step_s)) + 1)[1:-1]
                    for i, g in enumerate(gaps) if g > self.state_step_s]
            k = np.unique(np.concatenate([k, *fill]))
            T.append(k)
            N.append(np.full(len(k), n))
        return np.concatenate(T), np.concatenate(N)

    def digest_dict(self) -> dict:
        """Every input that changes the knots, the steps expanded (a cache key; not the frame rate)."""
        st, sf = self.steps()
        d = asdict(self)
        d.pop("rate_hz")
        d["steps"] = [st, sf]
        return d


# --- builders of the simple cases (issue 20's benchmark scenarios) ------------------------------

def uniform_resistivity(percent: float = 1.0, duration: float = 10.0, ramp_s: float = 1.0) -> TimelineSpec:
    """A uniform resistivity change of ``percent`` % reached at ``ramp_s`` (linear from 0 at the tare),
    contact impedance and drive unchanged, unloaded. (Modelled as dT = percent K at 1 %/K.)"""
    return TimelineSpec(duration=duration, temperature=Profile(((0.0, 0.0), (ramp_s, float(percent)))),
                        resistivity_per_k=0.01, contact_per_k=0.0)


def temperature_gradient(delta_t: float = 10.0, gradient: float = 0.3, resistivity_per_k: float = RESISTIVITY_PER_K,
                         contact_per_k: float = 0.0, axis=(1.0, 0.0, 0.0), duration: float = 10.0,
                         ramp_s: float = 1.0) -> TimelineSpec:
    """A temperature change of ``delta_t`` K with a gradient of +-``gradient`` of it along ``axis``."""
    return TimelineSpec(duration=duration, temperature=Profile(((0.0, 0.0), (ramp_s, float(delta_t)))),
                        resistivity_per_k=resistivity_per_k, contact_per_k=contact_per_k,
                        gradient=Profile(((0.0, float(gradient)),)), gradient_axis=tuple(map(float, axis)))


def drive_change(d: float = 0.003, duration: float = 10.0, ramp_s: float = 1.0) -> TimelineSpec:
    """The drive current changes by ``d`` (relative) over ``ramp_s``: every voltage x (1 + d)."""
    return TimelineSpec(duration=duration, drive=Profile(((0.0, 0.0), (ramp_s, float(d)))))


def contact_drift(max_change: float = 0.2, kind: str = "linear", duration: float = 10.0, seed: int = 0,
                  over_s: float | None = None) -> TimelineSpec:
    """Each electrode's contact impedance drifts on its own by up to +-``max_change``."""
    return TimelineSpec(duration=duration, contact_drift=ContactDrift(kind=kind, max=max_change, seed=seed,
                                                                      over_s=over_s))


def held_load_creep(magnitude: float = 20.0, elevation_deg: float = 90.0, azimuth_deg: float = 0.0,
                    creep: float = TYPICAL_CREEP_PER_DECADE, on: float = 1.0, off: float | None = None,
                    duration: float = 60.0) -> TimelineSpec:
    """A socket load applied at ``on`` and held (removed at ``off`` if given), creeping by ``creep``
    per decade and recovering after removal."""
    f = tuple(force_from_angles(magnitude, np.radians(elevation_deg), np.radians(azimuth_deg)))
    times, forces = (on,), (f,)
    if off is not None:
        times, forces = (on, off), (f, (0.0, 0.0, 0.0))
    return TimelineSpec(duration=duration, creep=creep, load_times=times, load_forces=forces)


def full_change(change: float = 0.024, gradient: float = 0.3, contact_per_k: float = CONTACT_PER_K,
                resistivity_per_k: float = RESISTIVITY_PER_K, ramp_s: float = 0.0, duration: float = 60.0,
                tasks: Tasks | None = None, axis=(1.0, 0.0, 0.0)) -> TimelineSpec:
    """A device changed in every way a temperature change moves it (docs/physics.md#device-changes): the
    rubber's mean resistivity by ``change`` (dT = change / ``resistivity_per_k`` K), +-``gradient`` of it
    across the block along ``axis``, every contact following its own temperature at ``contact_per_k``
    (-1 %/K: -3 % at +2.4 %, +3 % at -2.4 %); reached linearly at ``ramp_s`` from the tare's state, or with
    ``ramp_s`` 0 already there at the first frame (a restart long after the tare), under ``tasks``."""
    dT = float(change) / resistivity_per_k
    temp = Profile(((0.0, 0.0), (float(ramp_s), dT))) if ramp_s > 0 else Profile(((0.0, dT),))
    return TimelineSpec(duration=duration, temperature=temp, resistivity_per_k=resistivity_per_k,
                        contact_per_k=contact_per_k, gradient=Profile(((0.0, float(gradient)),)),
                        gradient_axis=tuple(map(float, axis)), tasks=tasks)


def warmup_30min(seed: int = 0, creep: float = TYPICAL_CREEP_PER_DECADE, duration: float = 1800.0) -> TimelineSpec:
    """The 30-minute warm-up: 15 K (an exponential approach, time constant 10 min, scaled to reach 15 K
    at 30 min, piecewise linear every 2 min, to 0.01 K) at +0.8 %/K with a 30 % gradient along +x, contacts
    -1 %/K, the drive +0.3 % (linear), creep ``creep`` per decade, and seeded contact tasks from 5 s."""
    t = np.arange(0.0, duration + 1e-9, 120.0)
    dT = np.round(15.0 * (1 - np.exp(-t / 600.0)) / (1 - np.exp(-duration / 600.0)), 2)  # as scenes/warmup_30min.yaml
    return TimelineSpec(duration=duration, temperature=Profile(tuple(zip(t.tolist(), dT.tolist()))),
                        resistivity_per_k=RESISTIVITY_PER_K, contact_per_k=CONTACT_PER_K, gradient=Profile(((0.0, 0.3),)),
                        drive=Profile(((0.0, 0.0), (duration, 0.003))), creep=creep, tasks=Tasks(seed=seed))


#: Issue 20's benchmark scenarios by name: builders of :class:`TimelineSpec` (keyword arguments as above).
SCENARIOS = {"uniform_resistivity": uniform_resistivity, "temperature_gradient": temperature_gradient,
             "drive_change": drive_change, "contact_drift": contact_drift, "held_load_creep": held_load_creep,
             "warmup_30min": warmup_30min, "full_change": full_change}


# --- the simulated device over time ------------------------------------------------------------

@dataclass
class TimelineState:
    """The true device state per frame: ``delta_t`` (K, the mean change), ``gradient`` (fraction),
    ``rho_change`` (the body's mean relative resistivity change, alpha dT), ``drive`` (the factor
    1 + d), ``force_eff`` (N, (n, 3), the creep's effective force) and ``contact`` ((n, 16), each
    electrode's contact impedance relative to the tare's)."""

    delta_t: np.ndarray
    gradient: np.ndarray
    rho_change: np.ndarray
    drive: np.ndarray
    force_eff: np.ndarray
    contact: np.ndarray = field(repr=False)

    def columns(self) -> dict[str, np.ndarray]:
        """The truth file's state columns (docs/formats.md#timeline), by name."""
        out = {"delta_t": self.delta_t, "gradient": self.gradient, "rho_change": self.rho_change,
               "drive": self.drive, "fx_eff": self.force_eff[:, 0], "fy_eff": self.force_eff[:, 1],
               "fz_eff": self.force_eff[:, 2]}
        out.update({f"contact_{e + 1}": self.contact[:, e] for e in range(self.contact.shape[1])})
        return out


class Timeline:
    """A :class:`TimelineSpec` played by an honestly simulated device (module docstring).

    Ready when constructed; the knots are solved (or read from the cache) on first use, all at once.
    Also a voltage source for :class:`~cstomo_sensor.board.sim.SimulatedBoard` (``frame(t, rng)``,
    ``truth(t)``).
    """

    def __init__(self, spec: TimelineSpec, sensor: str = DEFAULT_SENSOR, *, snr_db: float | None = DEFAULT_SNR_DB,
                 seed: int = 0, truth_mesh_size: float = TRUTH_MESH_SIZE,
                 mechanics_mesh_size: float = MECHANICS_MESH_SIZE, z_rel: float = CONTACT_MISMATCH,
                 jitter: float = ELECTRODE_JITTER, cache_dir=None, truth: Truth | None = None) -> None:
        self.spec = spec
        self.snr_db = snr_db
        self.seed = seed
        self.cache_dir = cache_dir
        self.truth_model = truth or Truth(load_sensor(sensor), truth_mesh_size, mechanics_mesh_size, z_rel, jitter,
                                          seed, cache_dir)
        self.steps = spec.steps()
        self.seconds: dict[str, float] = {}
        self.states_solved: int | None = None  # distinct states solved for the knots (None: read from the cache)

    @classmethod
    def from_scene(cls, scene, cache_dir=None, snr_db: float | None = None) -> Timeline:
        """From a scene file (or :class:`~cstomo_sensor.model.simulate.Scene`) with a ``timeline:``
        section; ``snr_db`` None takes the scene's."""
        base = path = None
        if not isinstance(scene, Scene):
            path, base = scene, Path(scene).parent
            scene = Scene.load(scene)
        if scene.timeline is None:
            raise ConfigError("the scene has no timeline: section (docs/formats.md#timeline)")
        try:  # before any mesh is built
            spec = TimelineSpec.from_dict(scene.timeline, base)
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}" if base is not None else str(err)) from None
        return cls(spec, snr_db=scene.snr_db if snr_db is None else snr_db,
                   seed=scene.seed, truth=scene.truth(cache_dir), cache_dir=cache_dir)

    # --- the device's state ------------------------------------------------------------------

    @cached_property
    def _axis_coordinate(self) -> tuple[np.ndarray, np.ndarray]:
        """(s per truth cell, s per electrode): the gradient's coordinate, volume mean 0, |s| <= 1."""
        fm = self.truth_model.forward
        a = np.asarray(self.spec.gradient_axis, float)
        a = a / np.linalg.norm(a)
        x = fm.mesh.centers @ a
        m = float(np.sum(fm.mesh.volumes * x) / np.sum(fm.mesh.volumes))
        h = float(np.max(np.abs(fm.mesh.points @ a - m)))
        xe = np.array([e.center for e in self.truth_model.device.electrodes]) @ a
        return (x - m) / h, np.clip((xe - m) / h, -1.0, 1.0)

    def _contact_factor(self, t) -> np.ndarray:
        """(len(t), n_electrodes) z_e(t) / z_e: temperature at the electrode and its own drift."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        sp = self.spec
        _, se = self._axis_coordinate
        dT = sp.temperature(t)[:, None] * (1.0 + sp.gradient(t)[:, None] * se[None, :])
        f = 1.0 + sp.contact_per_k * dT
        if sp.contact_drift is not None:
            nt, nc = sp.contact_drift.nodes(sp.duration, len(se))
            f = f * (1.0 + np.column_stack([np.interp(t, nt, nc[:, e]) for e in range(len(se))]))
        if np.any(f <= 0):
            raise ConfigError("timeline: a contact impedance reaches zero (contact_per_k x temperature too large)")
        return f

    def state(self, t) -> TimelineState:
        """The true state at times t (s), after :data:`duration` held (module docstring)."""
        t = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), 0.0, self.spec.duration)
        sp = self.spec
        dT = sp.temperature(t)
        c0 = self._contact_factor([0.0])[0]
        return TimelineState(delta_t=dT, gradient=sp.gradient(t), rho_change=sp.resistivity_per_k * dT,
                             drive=1.0 + sp.drive(t), force_eff=sp.force_eff(t),
                             contact=self._contact_factor(t) / c0)

    # --- the truth at one instant ------------------------------------------------------------

    @cached_property
    def _thetas(self) -> tuple[dict, np.ndarray]:
        """(index of each distinct non-zero force, theta of each (n_forces, n_cells)) on the truth mesh."""
        _, sf = self.steps
        index: dict[tuple, int] = {}
        for f in sf:
            if np.any(f) and tuple(f) not in index:
                index[tuple(f)] = len(index)
        t0 = time.perf_counter()
        tr = self.truth_model
        th = np.array([tr.theta(Load("socket", force=k)) for k in steps(index, log, "timeline: the mechanics of its "
                                                                        "loads")]).reshape(len(index), -1)
        self.seconds["mechanics"] = time.perf_counter() - t0
        return index, th

    def _sigma(self, t: float, n: int) -> np.ndarray:
        """Per-cell conductivity at time t with the first n steps in force."""
        sp, fm = self.spec, self.truth_model.forward
        _, sf = self.steps
        sigma = fm.sigma0
        if n and np.any(sf[:n]):
            index, th = self._thetas
            w = sp.creep_weights([t], n)[0]
            a = np.zeros(len(index))
            prev = np.zeros(3)
            for k in range(n):
                if np.any(sf[k]):
                    a[index[tuple(sf[k])]] += w[k]
                if np.any(prev):
                    a[index[tuple(prev)]] -= w[k]
                prev = sf[k]
            theta = a @ th
            sigma, broken = conductivity_of_theta(theta, self.truth_model.geometry.material)
            if broken.any():
                log.warning("t = %.3f s: %d cells beyond the percolation limit (clipped)", t, int(broken.sum()))
        s_cell, _ = self._axis_coordinate
        rho = 1.0 + sp.resistivity_per_k * float(sp.temperature(t)) * (1.0 + float(sp.gradient(t)) * s_cell)
        if np.any(rho <= 0):
            raise ConfigError("timeline: the resistivity factor reaches zero (resistivity_per_k x temperature)")
        return sigma / rho

    def _solve(self, t: float, n: int, solved: dict | None = None) -> np.ndarray:
        """Noise-free voltages without the drive at time t with the first n steps in force. ``solved``: the
        voltages of the states solved before, by a digest of their inputs (the cells' conductivity and the
        contacts' impedance): an equal state is not solved again. Equal states are common among the knots:
        a segment over which nothing changes (no warming, no creep) has equal knots at both ends, and every
        rest without warming is the unloaded state (a third of the knots of the suite's timelines)."""
        tr = self.truth_model
        z, sigma = tr.z * self._contact_factor([t])[0], self._sigma(t, n)
        if solved is None:
            return tr.forward.with_contact_impedance(z).voltages(sigma)
        key = hashlib.sha256(np.ascontiguousarray(z, float).tobytes() + np.ascontiguousarray(sigma, float).tobytes()).digest()
        if key not in solved:
            solved[key] = tr.forward.with_contact_impedance(z).voltages(sigma)
        return solved[key]

    @cached_property
    def reference(self) -> np.ndarray:
        """The noise-free unloaded frame at t = 0: the tare state."""
        return self._solve(0.0, 0) * (1.0 + float(self.spec.drive(0.0)))

    # --- knots, cached -----------------------------------------------------------------------

    def cache_key(self) -> str:
        tr = self.truth_model
        mesh = tr.forward.mesh
        digest = hashlib.sha256(np.ascontiguousarray(mesh.points).tobytes()
                                + np.ascontiguousarray(mesh.tets, dtype=np.int64).tobytes()).hexdigest()
        inputs = {"format": KNOTS_FORMAT, "geometry": tr.geometry.digest(), "device": tr.device.digest(),
                  "z": tr.z, "truth_mesh": digest, "spec": self.spec.digest_dict()}
        if np.any(self.steps[1]):
            m = tr.mechanics_mesh
            inputs["mechanics_mesh"] = hashlib.sha256(np.ascontiguousarray(m.points).tobytes()
                                                      + np.ascontiguousarray(m.tets, np.int64).tobytes()).hexdigest()
        return input_hash(inputs)

    @cached_property
    def knots(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(times (m,), steps in force (m,), noise-free voltages without the drive (m, n_meas))."""
        t0 = time.perf_counter()
        kt, kn = self.spec.knots()
        key = self.cache_key()
        path = Path(self.cache_dir or default_cache_dir()) / "timeline" / f"{self.truth_model.geometry.name}-{key}.npz"
        with build_lock(path):  # one process builds it, another waits and reads it (cache.build_lock)
            hit = cache_load(path, key, names=("t", "n", "v"))
            if hit is not None and np.array_equal(hit["t"], kt) and np.array_equal(hit["n"], kn):
                self.seconds["knots"] = time.perf_counter() - t0
                self.seconds["cache_hit"] = 1.0
                return hit["t"], hit["n"], hit["v"]
            log.info("timeline: solving the truth at %d knots (cached afterwards)", len(kt))
            solved: dict[bytes, np.ndarray] = {}  # an equal state is solved once (_solve)
            v = np.array([self._solve(t, n, solved) for t, n in steps(zip(kt, kn), log, "timeline: the truth at its knots",
                                                                      len(kt))])
            if "mechanics" in self.seconds:
                elasticity.release()  # every force is solved: free the mechanics' factor (hundreds of MB)
            cache_save(path, key, t=kt, n=kn, v=v)
            self.states_solved = len(solved)
            log.info("timeline: %d knots, %d states solved", len(kt), len(solved))
            self.seconds["knots"] = time.perf_counter() - t0
            self.seconds["cache_hit"] = 0.0
            return kt, kn, v

    @cached_property
    def _segments(self) -> dict[int, slice]:
        _, kn, _ = self.knots
        out, start = {}, 0
        for i in range(1, len(kn) + 1):
            if i == len(kn) or kn[i] != kn[start]:
                out[int(kn[start])] = slice(start, i)
                start = i
        return out

    def voltages(self, t) -> np.ndarray:
        """(len(t), n_meas) noise-free frames at times t: the knots interpolated linearly within the
        frame's segment, times the drive factor (module docstring)."""
        t = np.clip(np.atleast_1d(np.asarray(t, dtype=float)), 0.0, self.spec.duration)
        kt, _, kv = self.knots
        n = np.searchsorted(self.steps[0], t, side="right")
        out = np.empty((len(t), kv.shape[1]))
        for seg in np.unique(n):
            sel = np.flatnonzero(n == seg)
            sl = self._segments[int(seg)]
            ts = kt[sl]
            j = np.clip(np.searchsorted(ts, t[sel], side="right") - 1, 0, max(len(ts) - 2, 0))
            if len(ts) == 1:
                out[sel] = kv[sl][0]
                continue
            w = ((t[sel] - ts[j]) / (ts[j + 1] - ts[j]))[:, None]
            out[sel] = kv[sl][j] * (1 - w) + kv[sl][j + 1] * w
        return out * (1.0 + self.spec.drive(t))[:, None]

    def interpolation_error(self, n: int = 20, seed: int = 0) -> dict[str, float]:
        """The interpolation against direct solves at the midpoints of ``n`` knot intervals (random,
        seeded; the longest interval of each kind among them): max and rms of |V_interp - V_direct|
        over rms(reference), and the noise's std on the same scale (10^(-SNR/20))."""
        kt, kn, _ = self.knots
        inner = np.flatnonzero(kn[1:] == kn[:-1])
        inner = inner[kt[inner + 1] - kt[inner] > 1e-6]
        rng = np.random.default_rng(seed)
        pick = set(rng.choice(inner, size=min(n, len(inner)), replace=False).tolist()) if len(inner) else set()
        if len(inner):
            pick.add(int(inner[np.argmax(kt[inner + 1] - kt[inner])]))
        rms_ref = float(np.sqrt(np.mean(self.reference ** 2)))
        errs = []
        for i in sorted(pick):
            tm = 0.5 * (kt[i] + kt[i + 1])
            d = self._solve(tm, int(kn[i])) * (1.0 + float(self.spec.drive(tm))) - self.voltages([tm])[0]
            errs.append(np.abs(d) / rms_ref)
        e = np.array(errs) if errs else np.zeros((1, 1))
        return {"max": float(e.max()), "rms": float(np.sqrt(np.mean(e ** 2))), "intervals": len(errs),
                "noise": noise_std(1.0, self.snr_db) if self.snr_db is not None else 0.0}

    # --- frames --------------------------------------------------------------------------------

    def noise_rng(self) -> np.random.Generator:
        """The scene's noise generator (seed + 1, as :func:`~cstomo_sensor.model.simulate.simulate`)."""
        return np.random.default_rng(self.seed + 1)

    def tare(self, n: int = 1, rng: np.random.Generator | None = None) -> np.ndarray:
        """(n, n_meas) noisy unloaded frames of the tare state (t = 0)."""
        rng = rng or np.random.default_rng([self.seed, 22])
        return np.array([add_noise(self.reference, self.reference, self.snr_db, rng) for _ in range(n)])

    def frames(self, rate: float | None = None, t0: float = 0.0, t1: float | None = None,
               rng: np.random.Generator | None = None, chunk: int = 20000,
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, TimelineState]:
        """(times (n,), frames (n, n_meas) noise included, applied forces (n, 3), state) at ``rate``
        frames/s (default the spec's) over [t0, t1) (default the whole duration). The noise is drawn
        from ``rng`` (default :meth:`noise_rng`: the same frames for the same seed)."""
        rate = float(rate or self.spec.rate_hz)
        t1 = self.spec.duration if t1 is None else t1
        times = t0 + np.arange(int(np.ceil((t1 - t0) * rate - 1e-9))) / rate
        rng = rng or self.noise_rng()
        out = np.empty((len(times), len(self.reference)))
        for i in steps(range(0, len(times), chunk), log, f"timeline: {len(times)} frames, in chunks of {chunk}"):
            sl = slice(i, i + chunk)
            out[sl] = add_noise(self.voltages(times[sl]), self.reference, self.snr_db, rng)
        return times, out, self.spec.force(times), self.state(times)

    def frame(self, t: float, rng: np.random.Generator) -> np.ndarray:
        """One noisy frame at time t (the simulated board's voltage source): :meth:`voltages` of one
        time, without its array bookkeeping (a fifth of the cost at every board frame)."""
        t = min(max(float(t), 0.0), self.spec.duration)
        kt, _, kv = self.knots
        sl = self._segments[int(np.searchsorted(self.steps[0], t, side="right"))]
        ts, vs = kt[sl], kv[sl]
        if len(ts) == 1:
            v = vs[0]
        else:
            j = min(max(int(np.searchsorted(ts, t, side="right")) - 1, 0), len(ts) - 2)
            w = (t - ts[j]) / (ts[j + 1] - ts[j])
            v = vs[j] * (1 - w) + vs[j + 1] * w
        d = self.spec.drive
        v = v * (1.0 + (d.points[0][1] if len(d.points) == 1 else float(d(t))))
        return add_noise(v, self.reference, self.snr_db, rng)

    def truth(self, t: float) -> np.ndarray:
        """The applied socket force at time t, N."""
        return self.spec.force([t])[0]

    @property
    def duration(self) -> float:
        return self.spec.duration

    def prepare(self) -> Timeline:
        """Solve (or read) every knot now, so that frames never wait on a solve; returns self."""
        self.knots  # noqa: B018
        _ = self._segments, self.reference
        return self


def is_timeline_scene(path) -> bool:
    """True when the scene file has a ``timeline:`` section."""
    return Scene.load(path).timeline is not None


def write_truth(path, times: np.ndarray, forces: np.ndarray, state: TimelineState) -> None:
    """A forces file (docs/formats.md#forces-file) with the time and the state columns after the
    standard ones (docs/formats.md#timeline)."""
    mag, el, az = force_angles_deg(forces)
    cols = {"time": times, **state.columns()}
    lines = [FORCES_HEADER + "," + ",".join(cols)]
    table = np.column_stack([forces, mag, el, az, *cols.values()])
    fmt = ",".join(["%d"] + ["%.9g"] * table.shape[1])
    lines += [fmt % (i, *row) for i, row in enumerate(table)]
    with atomic_write(path) as out:
        out.write(("\n".join(lines) + "\n").encode())


def simulate_timeline_files(scene_path, out_dir, cache_dir=None) -> Timeline:
    """``cstomo simulate`` of a timeline scene: reference.csv (one noisy unloaded frame of the tare
    state), frames.csv (every frame at the timeline's ``rate_hz``) and truth.csv (the applied force,
    the time and the state; docs/formats.md#timeline)."""
    tl = Timeline.from_scene(scene_path, cache_dir)
    rng = tl.noise_rng()
    ref = tl.tare(1, rng)
    times, frames, forces, state = tl.frames(rng=rng)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    note = (f"simulated from {scene_path} over {tl.spec.duration:g} s at {tl.spec.rate_hz:g} frames/s "
            f"(honest: independent mesh, mismatch, SNR {tl.snr_db} dB; times in truth.csv)")
    write_frames(out / "reference.csv", ref, comment=note + ", unloaded at t = 0 (the tare)")
    write_frames(out / "frames.csv", frames, comment=note)
    write_truth(out / "truth.csv", times, forces, state)
    return tl


def with_spec(tl: Timeline, **changes) -> Timeline:
    """The same device with some of the spec's fields changed (a new timeline, same truth)."""
    return Timeline(replace(tl.spec, **changes), snr_db=tl.snr_db, seed=tl.seed, cache_dir=tl.cache_dir,
                    truth=tl.truth_model)


__all__ = ["ContactDrift", "Profile", "SCENARIOS", "Tasks", "Timeline", "TimelineSpec", "TimelineState",
           "contact_drift", "drive_change", "full_change", "held_load_creep", "is_timeline_scene", "simulate_timeline_files",
           "temperature_gradient", "uniform_resistivity", "warmup_30min", "with_spec", "write_truth"]
