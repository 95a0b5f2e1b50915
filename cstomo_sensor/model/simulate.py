"""Honest simulation (docs/physics.md#honest-simulation) and scene files.

The truth is simulated on an independent tetrahedralisation finer than any model mesh, with
electrode positions jittered by up to 0.2 mm and contact impedances varied by +-20 % per electrode
(seeded), plus white noise at the scene's SNR. Loads go through the mechanics (only when the scene
has mechanical loads), the material law (volumetric compression -> conductivity) and the forward
model. The reference frame is the same simulated device, unloaded.

Scene file (YAML)::

    sensor: cuboid_joint          # preset or geometry file
    snr_db: 60                    # noise (docs/physics.md#noise); omit or null for none
    seed: 1
    truth_mesh_size: 0.003        # m; the independent mesh
    mechanics_mesh_size: 0.004    # m
    mismatch: {contact_impedance: 0.2, electrode_jitter: 0.0002}
    frames_per_load: 1
    loads:
      - {socket: {magnitude: 20, elevation_deg: 30, azimuth_deg: 0}}
      - {socket: {force: [0, 0, -20]}}
      - {patches: [{shape: square, size: 0.01, center: [0, 0]}], total_force: 20}
      - {patches: [{shape: circle, radius: 0.004, center: [0.005, 0.01], face: +y}], total_force: 10}
                                    # a side face of a cuboid; center in the face's (x, z), m
      - {inclusion: {center: [0, 0, 0.01], radius: 0.003, contrast: 0.5}}   # no mechanics

A scene with a ``timeline:`` section instead of ``loads`` is a device over time (temperature, drive,
contacts, creep, contact tasks): model/timeline.py reads it (docs/formats.md#timeline).
"""
from __future__ import annotations

import hashlib
import logging
import math
import os
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import yaml

from ..angles import force_from_angles
from ..cache import build_lock, cache_load, cache_save, default_cache_dir, input_hash
from ..errors import ConfigError
from ..frames_io import load_index, read_load_script, write_forces, write_frames
from ..progress import steps
from ..settings import DEFAULT_SENSOR, MAX_LOAD, MESH_SIZE_RANGE
from . import elasticity
from .cem import ForwardModel
from .geometry import DEFAULT_SNR_DB, Electrode, SensorGeometry, load_sensor, noise_std
from .material import conductivity_of_theta
from .mesh import MeshSpec, TetMesh, build_mesh

log = logging.getLogger(__name__)

#: The honest simulation's defaults (docs/physics.md#honest-simulation; a scene file may set each): the truth's independent
#: mesh and its mechanics mesh (m), and the device's mismatch: contact impedances scaled by
#: U(1 -+ CONTACT_MISMATCH) per electrode, electrodes moved by up to ELECTRODE_JITTER m.
TRUTH_MESH_SIZE = 3.0e-3
MECHANICS_MESH_SIZE = 4.0e-3
CONTACT_MISMATCH = 0.2
ELECTRODE_JITTER = 2.0e-4
#: A scene file's keys (docs/formats.md#scene-file; ``cstomo simulate --help``) and those of its ``mismatch``:
#: any other key is refused, named.
SCENE_KEYS = ("sensor", "snr_db", "seed", "truth_mesh_size", "mechanics_mesh_size", "mismatch", "frames_per_load",
              "loads", "timeline")
MISMATCH_KEYS = ("contact_impedance", "electrode_jitter")

#: Version of the simulated frames' cache entries (:meth:`Truth.frames`): bump it when the physics of
#: the simulation changes in a way its inputs do not show (mechanics, material law, forward model).
TRUTH_FORMAT = 1
#: Version of a load's mechanics entries (:meth:`Truth.theta`): bump it when the elasticity or the loads'
#: solution change in a way their inputs do not show.
MECHANICS_FORMAT = 1


def add_noise(v: np.ndarray, reference: np.ndarray, snr_db: float | None, rng: np.random.Generator) -> np.ndarray:
    """White Gaussian noise with std rms(reference) * 10^(-SNR/20) (:func:`~.geometry.noise_std`); None = no noise."""
    if snr_db is None:
        return np.array(v, dtype=float)
    std = noise_std(reference, snr_db)
    return v + rng.normal(0.0, std, np.shape(v))


def mismatched(geometry: SensorGeometry, rng: np.random.Generator, z_rel: float = CONTACT_MISMATCH,
               jitter: float = ELECTRODE_JITTER) -> tuple[SensorGeometry, np.ndarray]:
    """The geometry with each electrode moved by up to ``jitter`` m within its face, and
    per-electrode contact impedances scaled by U(1 - z_rel, 1 + z_rel)."""
    out = []
    for e in geometry.electrodes:
        n = np.asarray(e.normal)
        t1 = np.cross(n, [0, 0, 1.0])
        t1 /= np.linalg.norm(t1)
        r, a = jitter * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        c = np.asarray(e.center) + r * (np.cos(a) * t1 + np.sin(a) * np.array([0, 0, 1.0]))
        if geometry.shape == "cylinder":  # stay on the wall
            c[:2] *= geometry.size[0] / np.hypot(c[0], c[1])
        out.append(Electrode(e.name, tuple(c), e.normal, e.radius))
    z = geometry.contact_impedance * rng.uniform(1 - z_rel, 1 + z_rel, geometry.n_electrodes)
    return geometry.with_electrodes(tuple(out)), z


@dataclass(frozen=True)
class Load:
    """One load: a socket force (N, wrench frame), pressure patches, or a conductivity inclusion."""

    kind: str  # "socket" | "patches" | "inclusion" | "none"
    force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    patches: tuple = ()
    inclusion: tuple = ()  # (cx, cy, cz, radius, contrast)

    @classmethod
    def from_dict(cls, d: dict) -> Load:
        """A load of a scene file (docs/formats.md#scene-file); :class:`ConfigError` naming it and what
        each kind takes when a key is missing or a value of the wrong shape."""
        try:
            return cls._from_dict(d)
        except ConfigError:
            raise
        except (KeyError, TypeError, ValueError, IndexError) as err:
            why = f"missing {err}" if isinstance(err, KeyError) else str(err)
            raise ConfigError(f"load {d!r}: {why}; expected socket: {{force: [fx, fy, fz]}} or {{magnitude: N, "
                              "elevation_deg: D, azimuth_deg: D}, patches: [{shape:, size: or radius:, center:, "
                              "face:}] with total_force: N, or inclusion: {center: [x, y, z], radius: m, contrast: c} "
                              "(docs/formats.md#scene-file)") from None

    @classmethod
    def _from_dict(cls, d: dict) -> Load:
        if not isinstance(d, dict) or len(d.keys() - {"total_force"}) != 1:
            raise ConfigError(f"load {d!r}: expected one of socket:, patches: (+ total_force:), inclusion:")
        if "socket" in d:
            s = d["socket"]
            if "force" in s:
                f = tuple(float(v) for v in s["force"])
                if len(f) != 3:
                    raise ValueError(f"socket force {s['force']!r} has {len(f)} components, not 3")
            else:
                f = tuple(force_from_angles(float(s["magnitude"]), np.radians(float(s["elevation_deg"])),
                                            np.radians(float(s.get("azimuth_deg", 0.0)))))
            return cls("socket", force=f)
        if "patches" in d:
            total = float(d.get("total_force", 0.0))
            if total <= 0:
                raise ConfigError(f"total_force={d.get('total_force')!r}: expected a positive force in N")
            patches = tuple((p["shape"], float(p.get("size", p.get("radius", 0.0))), tuple(p.get("center", (0, 0))),
                             str(p.get("face", "top"))) for p in d["patches"])
            inward = {"top": (0, 0, -1), "+x": (-1, 0, 0), "-x": (1, 0, 0), "+y": (0, -1, 0), "-y": (0, 1, 0)}
            face = patches[0][3] if patches else "top"
            if face not in inward:
                raise ConfigError.bad_value("patches.face", face, f"one of {list(inward)}")
            return cls("patches", force=tuple(total * float(c) for c in inward[face]), patches=patches)
        if "inclusion" in d:
            i = d["inclusion"]
            return cls("inclusion", inclusion=(*map(float, i["center"]), float(i["radius"]), float(i["contrast"])))
        raise ConfigError(f"load {d!r}: unknown kind; expected socket, patches or inclusion")

    @property
    def force_vector(self) -> np.ndarray:
        return np.asarray(self.force, dtype=float)


class Truth:
    """The simulated device: an independent mesh, mismatched electrodes, mechanics on demand.

    Ready when constructed; nothing is built before a load needs it (the forward model on the
    first voltage, the mechanics mesh on the first mechanical load).
    """

    def __init__(self, geometry: SensorGeometry, truth_h: float = TRUTH_MESH_SIZE,
                 mechanics_h: float = MECHANICS_MESH_SIZE, z_rel: float = CONTACT_MISMATCH,
                 jitter: float = ELECTRODE_JITTER, seed: int = 0, cache_dir=None) -> None:
        self.geometry = geometry
        self.truth_h, self.mechanics_h = truth_h, mechanics_h
        self.cache_dir = cache_dir
        self.device, self.z = mismatched(geometry, np.random.default_rng(seed), z_rel, jitter)
        self._theta_cache: dict[tuple, np.ndarray] = {}

    @cached_property
    def truth_mesh(self) -> TetMesh:
        return build_mesh(self.geometry, MeshSpec(h=self.truth_h), self.cache_dir)

    @cached_property
    def forward(self) -> ForwardModel:
        return ForwardModel(self.device, self.truth_mesh, contact_impedance=self.z)

    @cached_property
    def mechanics_mesh(self) -> TetMesh:
        return build_mesh(self.geometry, MeshSpec(h=self.mechanics_h, h_electrode=self.mechanics_h), self.cache_dir)

    @cached_property
    def _sampler(self) -> elasticity.PointSampler:
        """The truth mesh's cell centres located in the mechanics mesh (once, for every load)."""
        m = self.mechanics_mesh
        return elasticity.point_sampler(m.points, m.tets, self.forward.mesh.centers)

    @cached_property
    def reference(self) -> np.ndarray:
        """Noise-free unloaded frame of the simulated device."""
        return self.forward.voltages()

    def theta(self, load: Load) -> np.ndarray:
        """Volumetric compression at the truth mesh's cell centres."""
        key = (load.kind, load.force, load.patches)
        if key not in self._theta_cache:
            self._theta_cache[key] = self._sampler(self._theta_vertices(load))
        return self._theta_cache[key]

    def _theta_vertices(self, load: Load) -> np.ndarray:
        """The load's volumetric compression at the vertices of each mechanics cell
        (``MechanicsSolution.theta_vertices``), from the disk cache or solved (then saved there).

        The entry is keyed by every input of the solve: :data:`MECHANICS_FORMAT`, the geometry (its
        material and body; the simulated device's electrodes and contacts do not enter the mechanics),
        the content of the mechanics mesh, and the load; so every truth of one sensor shares a load's
        mechanics (other seeds, truth meshes, timelines, processes), and a load already solved costs no
        factorisation of the elasticity (10-30 s on the 4 mm mesh) in a process that needs nothing else.
        """
        m = self.mechanics_mesh
        key = input_hash({"format": MECHANICS_FORMAT, "geometry": self.geometry.digest(), "mesh": _mesh_digest(m),
                          "load": [load.kind, list(load.force), repr(load.patches)]})
        path = Path(self.cache_dir or default_cache_dir()) / "mechanics" / f"{self.geometry.name}-{key}.npz"
        with build_lock(path):  # one process solves it, another waits and reads it (cache.build_lock)
            hit = cache_load(path, key, names=("theta",))
            if hit is not None and hit["theta"].shape == (len(m.tets), 4):
                return hit["theta"]
            if load.kind == "socket":
                sol = elasticity.solve_socket_load(m.points, m.tets, self.geometry, load.force_vector)
            else:
                patches = [{"shape": s, ("size" if s == "square" else "radius"): v, "center": c, "face": f}
                           for s, v, c, f in load.patches]
                sol = elasticity.solve_patch_load(m.points, m.tets, self.geometry, patches,
                                                  float(np.linalg.norm(load.force)))
            try:
                cache_save(path, key, theta=sol.theta_vertices)
            except OSError as err:  # a read-only cache: solved again next time, nothing else
                log.warning("a load's mechanics not cached (%s): %s", path, err)
            return sol.theta_vertices

    def conductivity(self, load: Load | tuple[Load, ...]) -> np.ndarray:
        """Per-cell conductivity of the truth mesh under ``load``, or under several mechanical loads
        acting together (socket and patches: linear elasticity adds their compressions)."""
        fm = self.forward
        if isinstance(load, tuple):
            sigma, _ = conductivity_of_theta(sum(self.theta(ld) for ld in load), self.geometry.material)
            return sigma
        if load.kind == "none" or (load.kind == "socket" and not any(load.force)):
            return fm.sigma0
        if load.kind == "inclusion":
            cx, cy, cz, r, contrast = load.inclusion
            inside = np.linalg.norm(fm.mesh.centers - [cx, cy, cz], axis=1) <= r
            return fm.sigma0 * np.where(inside, 1.0 + contrast, 1.0)
        sigma, broken = conductivity_of_theta(self.theta(load), self.geometry.material)
        if broken.any():
            log.warning("%d cells beyond the percolation limit (clipped)", int(broken.sum()))
        return sigma

    def voltages(self, load: Load | tuple[Load, ...]) -> np.ndarray:
        """Noise-free frame under ``load`` (or several loads together, see :meth:`conductivity`)."""
        return self.forward.voltages(self.conductivity(load))

    def frames(self, loads: list[Load]) -> tuple[np.ndarray, np.ndarray]:
        """(noise-free unloaded reference (n_meas,), noise-free frames (len(loads), n_meas)) of this
        device, from the disk cache or computed (then saved there; then the mechanics' factor is freed).

        The entry is keyed by every input of the numbers: :data:`TRUTH_FORMAT`, the geometry (all its
        fields, material included), the simulated device (its moved electrodes and contact
        impedances), the content of the truth mesh and, when a load is mechanical, of the mechanics
        mesh, and the loads in order; so another seed, mesh, sensor file or load script never reuses it.
        """
        mechanical = any(ld.kind in ("socket", "patches") and any(ld.force) for ld in loads)
        meshes = [self.truth_mesh] + ([self.mechanics_mesh] if mechanical else [])
        key = input_hash({
            "format": TRUTH_FORMAT, "geometry": self.geometry.digest(),
            "device": [list(e.center) + [e.radius] for e in self.device.electrodes], "z": self.z,
            "meshes": [_mesh_digest(m) for m in meshes],
            "loads": [[ld.kind, list(ld.force), repr(ld.patches), list(ld.inclusion)] for ld in loads],
        })
        path = Path(self.cache_dir or default_cache_dir()) / "truth" / f"{self.geometry.name}-{key}.npz"
        with build_lock(path):  # one process builds it, another waits and reads it (cache.build_lock)
            hit = cache_load(path, key, names=("reference", "frames"))
            if hit is not None and hit["frames"].shape[0] == len(loads):
                return hit["reference"], hit["frames"]
            t0 = time.perf_counter()
            frames = np.array([self.voltages(ld) for ld in steps(loads, log, "simulated device: its loads")]
                              ).reshape(len(loads), -1)
            if mechanical:
                elasticity.release()  # every load is computed: free the mechanics' factor (hundreds of MB)
            reference = self.reference
            try:
                cache_save(path, key, reference=reference, frames=frames)
            except OSError as err:  # a read-only cache costs the next start the same time, nothing else
                log.warning("simulated frames not cached (%s): %s", path, err)
            log.info("simulated device: %d loads in %.1f s (cached in %s)", len(loads), time.perf_counter() - t0, path)
            return reference, frames


def _mesh_digest(mesh: TetMesh) -> str:
    """SHA-256 (24 hex digits) of a mesh's points and cells: the mesh itself, not its inputs (a
    re-meshed geometry may differ)."""
    h = hashlib.sha256(np.ascontiguousarray(mesh.points, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.tets, dtype=np.int64).tobytes())
    return h.hexdigest()[:24]


@dataclass(frozen=True)
class Scene:
    """A scene file's content (see the module docstring)."""

    sensor: str
    loads: tuple[Load, ...]
    snr_db: float | None = DEFAULT_SNR_DB
    seed: int = 0
    truth_mesh_size: float = TRUTH_MESH_SIZE
    mechanics_mesh_size: float = MECHANICS_MESH_SIZE
    z_rel: float = CONTACT_MISMATCH
    jitter: float = ELECTRODE_JITTER
    frames_per_load: int = 1
    timeline: dict | None = None  # a device over time: read by model/timeline.py (it replaces loads)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Scene:
        p = Path(path)
        if not p.is_file():
            raise ConfigError(f"scene file {str(p)!r}: not found; expected a scene YAML file (docs/formats.md#scene-file, "
                              "examples in scenes/)")
        d = yaml.safe_load(p.read_text()) or {}
        if not isinstance(d, dict):
            raise ConfigError(f"{p}: expected a mapping of the keys {list(SCENE_KEYS)}")
        if ("loads" in d) == ("timeline" in d):
            raise ConfigError(f"{p}: " + ("give either 'loads' or 'timeline', not both" if "loads" in d
                                          else "missing key 'loads' (or 'timeline')"))
        mm = d.get("mismatch") or {}
        for where, m, keys in (("", d, SCENE_KEYS), ("mismatch.", mm, MISMATCH_KEYS)):
            unknown = sorted(str(k) for k in m if k not in keys) if isinstance(m, dict) else []
            if unknown:
                raise ConfigError(f"{p}: unknown keys {[where + k for k in unknown]}; expected some of "
                                  f"{[where + k for k in keys]}")
        sensor = str(d.get("sensor", DEFAULT_SENSOR))
        if not Path(sensor).is_absolute() and Path(sensor).suffix in (".yaml", ".yml"):
            sensor = str(p.parent / sensor)
        if "timeline" in d and not isinstance(d["timeline"], dict):
            raise ConfigError(f"{p}: timeline: expected a mapping (docs/formats.md#timeline)")
        loads = []
        for i, x in enumerate(d.get("loads") or ()):
            try:
                loads.append(Load.from_dict(x))
            except ConfigError as err:
                raise ConfigError(f"{p}: loads[{i}]: {err}") from None
            magnitude = float(np.linalg.norm(loads[-1].force))
            if loads[-1].kind == "socket" and not magnitude <= MAX_LOAD:  # before any mesh is built
                raise ConfigError(f"{p}: loads[{i}] (socket) is {magnitude:g} N; expected a magnitude of "
                                  f"0..{MAX_LOAD:g} N")
        lo, hi = MESH_SIZE_RANGE
        snr_db = d.get("snr_db", DEFAULT_SNR_DB)
        if snr_db is not None:  # checked; kept as written (an int stays one: the cache keys see it)
            x = _scene_value(p, "snr_db", snr_db, "a number (dB) or null", -math.inf, math.inf)
            snr_db = snr_db if isinstance(snr_db, (int, float)) else x
        return cls(sensor=sensor, loads=tuple(loads),
                   snr_db=snr_db,
                   seed=int(_scene_value(p, "seed", d.get("seed", 0), "an integer >= 0", integer=True)),
                   truth_mesh_size=_scene_value(p, "truth_mesh_size", d.get("truth_mesh_size", TRUTH_MESH_SIZE),
                                                f"{lo:g}..{hi:g} m", lo, hi),
                   mechanics_mesh_size=_scene_value(p, "mechanics_mesh_size",
                                                    d.get("mechanics_mesh_size", MECHANICS_MESH_SIZE),
                                                    f"{lo:g}..{hi:g} m", lo, hi),
                   z_rel=_scene_value(p, "mismatch.contact_impedance", mm.get("contact_impedance", CONTACT_MISMATCH),
                                      "a fraction 0..1", 0.0, 1.0),
                   jitter=_scene_value(p, "mismatch.electrode_jitter", mm.get("electrode_jitter", ELECTRODE_JITTER),
                                       "a distance >= 0 m", 0.0),
                   frames_per_load=int(_scene_value(p, "frames_per_load", d.get("frames_per_load", 1),
                                                    "an integer >= 1", 1, integer=True)),
                   timeline=d.get("timeline"))

    def truth(self, cache_dir=None) -> Truth:
        return Truth(load_sensor(self.sensor), self.truth_mesh_size, self.mechanics_mesh_size, self.z_rel,
                     self.jitter, self.seed, cache_dir)


def _scene_value(path: Path, key: str, value: object, expected: str, lo: float = 0.0, hi: float = math.inf, *,
                 integer: bool = False) -> float:
    """A scene file's number ``key``, checked before any mesh is built: else one :class:`ConfigError`
    naming the file, the key, the value and what was expected (before: a traceback, e.g. ``snr_db: sixty``)."""
    try:  # a string too: YAML reads 3e-3 (no dot) as one
        x = float(value) if isinstance(value, (int, float, str)) and not isinstance(value, bool) else math.nan
    except ValueError:
        x = math.nan
    if not (lo <= x <= hi and (x.is_integer() or not integer)):
        raise ConfigError(f"{path}: {key}={value!r}: expected {expected}")
    return x


def _no_timeline(scene: Scene) -> None:
    if scene.timeline is not None:
        raise ConfigError("a scene with a timeline is a device over time: simulate it with "
                          "cstomo_sensor.model.timeline.Timeline.from_scene (docs/formats.md#timeline)")


def simulate(scene: Scene, cache_dir=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(reference (n_meas,), frames (n, n_meas), true forces (n, 3)) of a scene, noise included."""
    _no_timeline(scene)
    truth = scene.truth(cache_dir)
    reference, volts = truth.frames(list(scene.loads))  # cached, keyed by every input: a second run reads them
    rng = np.random.default_rng(scene.seed + 1)
    ref = add_noise(reference, reference, scene.snr_db, rng)
    frames, forces = [], []
    for load, v in zip(scene.loads, volts):
        for _ in range(scene.frames_per_load):
            frames.append(add_noise(v, reference, scene.snr_db, rng))
            forces.append(load.force_vector)
    return ref, np.array(frames), np.array(forces)


def simulate_scene_files(scene_path, out_dir, cache_dir=None) -> None:
    """``cstomo simulate``: write reference.csv, frames.csv and truth.csv (docs/formats.md)."""
    scene = Scene.load(scene_path)
    ref, frames, forces = simulate(scene, cache_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    note = f"simulated from {scene_path} (honest: independent mesh, mismatch, SNR {scene.snr_db} dB)"
    write_frames(out / "reference.csv", ref[None], comment=note + ", unloaded")
    write_frames(out / "frames.csv", frames, comment=note)
    write_forces(out / "truth.csv", forces)


class VoltageSource:
    """Frames of a simulated device following a load script or a scene, for the simulated board.

    ``frame(t, rng)`` gives the noisy frame at time t (seconds from start); ``truth(t)`` the force.
    Every load is computed up front (so streaming never stalls on a solve), or read from the disk
    cache of :meth:`Truth.frames` (a warm ``cstomo board-sim`` is ready in about a second).
    """

    def __init__(self, truth: Truth, times: np.ndarray, loads: list[Load], snr_db: float | None,
                 period: float | None = None) -> None:
        self.truth_model = truth
        self.times = np.asarray(times, dtype=float)
        self.loads = loads
        self.snr_db = snr_db
        self.period = period
        self._ref, self._frames = truth.frames(list(loads))

    @classmethod
    def from_args(cls, sensor: str = DEFAULT_SENSOR, scene: str | None = None, load_script: str | None = None,
                  snr_db: float | None = None, seed: int = 0, cache_dir=None,
                  hold: float = 1.0) -> VoltageSource:
        """From a load script (``time,fx,fy,fz``) or a scene (each load held ``hold`` seconds); ``snr_db``
        None takes the scene's, or :data:`DEFAULT_SNR_DB` for a load script."""
        if (scene is None) == (load_script is None):
            raise ConfigError("give exactly one of scene=FILE or load_script=FILE.csv")
        if scene is not None:
            sc = Scene.load(scene)
            _no_timeline(sc)
            truth = sc.truth(cache_dir)
            return cls(truth, hold * np.arange(len(sc.loads)), list(sc.loads),
                       sc.snr_db if snr_db is None else snr_db)
        times, forces = read_load_script(load_script)
        truth = Truth(load_sensor(sensor), seed=seed, cache_dir=cache_dir)
        return cls(truth, times, [Load("socket", force=tuple(f)) for f in forces],
                   DEFAULT_SNR_DB if snr_db is None else snr_db)

    def truth(self, t: float) -> np.ndarray:
        i = load_index(self.times, t)
        return np.zeros(3) if i < 0 else self.loads[i].force_vector

    def frame(self, t: float, rng: np.random.Generator) -> np.ndarray:
        i = load_index(self.times, t)
        v = self._ref if i < 0 else self._frames[i]
        return add_noise(v, self._ref, self.snr_db, rng)

    @property
    def duration(self) -> float:
        return float(self.times[-1]) if len(self.times) else 0.0

