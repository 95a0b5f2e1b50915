"""Measure the first-tare table of docs/node.md#tare (issue 35, item 2): a node's first start under a load.

    PYTHONPATH=. OPENBLAS_NUM_THREADS=1 python test/first_tare_table.py [--estimator model|linear]

Honest frames (cstomo_sensor.model.simulate.Truth: an independent finer mesh, mismatched electrodes and
contacts; 60 dB noise) of four devices: the committed bag's (seed 7), the planar scene's
(scenes/cuboid_planar_60db.yaml), and the two corner devices (scenes/cuboid_device_a_60db.yaml,
scenes/cuboid_device_b_60db.yaml), each unloaded and under 2, 5, 10 and 20 N in eight directions. The
node's own pipeline (default settings, the given estimator; built into the cache on a first run).

Two tables:

1. **Against the model's reference** (what a first tare could compare with): the candidate tare's change
   from the model's predicted frame, its global factor divided out and projected off the uniform, the
   contacts' (4) and the gradient's (3) directions, through the estimator retrained blind to them (the
   rule force/reference/tare_rules.py applies between two tares): the "load" each device reads unloaded, and under each
   load.
2. **After the first tare** (force/reference/first_tare.py): a FrameStream tares on 50 frames under the load, reads
   100 frames of it, then 200 unloaded frames: the smallest load whose first tare is dropped once the
   load goes, by direction and device.
3. A true first tare (taken unloaded), then every load of the device: never dropped, and the largest
   Fz the frames read over the watch's run of frames.
"""
from __future__ import annotations

import argparse
import logging
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

DIRECTIONS = {  # name: (elevation, azimuth) deg; the socket carries elevations 15..90 deg
    "straight down": (90, 0), "45 deg, az 0": (45, 0), "45 deg, az 135": (45, 135), "60 deg, az 270": (60, 270),
    "30 deg, az 225": (30, 225), "lateral x (el 15)": (15, 0), "lateral y (el 15)": (15, 90),
    "lateral -x (el 15)": (15, 180),
}
MAGNITUDES = (2.0, 5.0, 10.0, 20.0)
DEVICES = {"bag (seed 7)": None, "planar scene": "scenes/cuboid_planar_60db.yaml",
           "device_a": "scenes/cuboid_device_a_60db.yaml", "device_b": "scenes/cuboid_device_b_60db.yaml"}
SNR_DB = 60.0
TARE_FRAMES = 50


def load_list():
    from cstomo_sensor.angles import force_from_angles
    from cstomo_sensor.model.simulate import Load

    return [Load("socket", force=tuple(float(v) for v in force_from_angles(m, np.radians(el), np.radians(az))))
            for el, az in DIRECTIONS.values() for m in MAGNITUDES]


def device_frames(scene):
    """(noise-free reference, frames (directions x magnitudes, n_meas)) of a device (cached)."""
    from cstomo_sensor.model.geometry import load_sensor
    from cstomo_sensor.model.simulate import Scene, Truth

    truth = Truth(load_sensor("cuboid_joint"), seed=7) if scene is None else Scene.load(ROOT / scene).truth()
    return truth.frames(load_list())


def model_figure(pipe):
    """The figure of table 1 for a candidate tare (volts): the blind estimate's norm (N)."""
    from cstomo_sensor.force.estimators.scale_fit import gradient_directions
    from cstomo_sensor.force.reference.files import ScaleReport

    m = pipe.model
    q, _ = np.linalg.qr(np.vstack([m.model_reference / m.v_scale, m.contact, gradient_directions(m)]).T)

    def project(y):
        return y - (y @ q) @ q.T

    blind = pipe.estimator.with_set(pipe.estimator.forces, project(np.asarray(pipe.estimator.y)))

    def figure(v):
        c = ScaleReport.of(v, m.model_reference).factor
        return float(np.linalg.norm(blind.estimate(project((v / c - m.model_reference) / m.v_scale))))

    return figure


def run_stream(pipe, frames, tare_file):
    """Push ``frames`` ((n, n_meas) volts, one per 10 ms) through a FrameStream from a first start; returns
    (the frame index at which the first tare was dropped, None if never; forces (n, 3), NaN without output)."""
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream

    Path(tare_file).unlink(missing_ok=True)  # a first start: no saved tare, no reference
    pipe.drop_reference()
    s = FrameStream(pipe, StreamConfig.offline(tare_frames=TARE_FRAMES), tare_file=tare_file)
    s.init_reference(tare_on_start=False)
    dropped, forces = None, np.full((len(frames), 3), np.nan)
    for i, v in enumerate(frames):
        had = s.first_tare is not None
        out = s.push(v, stamp_ns=int((i + 1) * 1e7))
        if out is not None and out.result.valid:
            forces[i] = out.result.force
        if had and s.first_tare is None and s.tares.pending and dropped is None:
            dropped = i
    s.close()
    Path(tare_file).unlink(missing_ok=True)
    return dropped, forces


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--estimator", default="model", choices=("model", "linear"))
    args = ap.parse_args()
    logging.basicConfig(level=logging.ERROR)
    from cstomo_sensor.force.reference.first_tare import PULL_FRAMES, PULL_MIN_N
    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.frame_path.pipeline import Pipeline
    from cstomo_sensor.model.simulate import add_noise

    t0 = time.perf_counter()
    pipe = Pipeline.build(PipelineConfig(estimator=args.estimator))
    figure = model_figure(pipe)
    rng = np.random.default_rng(35)
    data = {name: device_frames(scene) for name, scene in DEVICES.items()}
    print(f"# estimator {args.estimator}, {SNR_DB:g} dB, tares of {TARE_FRAMES} frames; devices ready in "
          f"{time.perf_counter() - t0:.0f} s")

    def noisy(v, ref, n):
        return np.array([add_noise(v, ref, SNR_DB, rng) for _ in range(n)])

    print("\n## 1. a candidate first tare against the model's reference: the 'load' it reads (N)\n")
    shown = ("straight down", "45 deg, az 0", "lateral x (el 15)")
    print("| device | unloaded | " + " | ".join(f"under 20 N {d}" for d in shown) + " |")
    print("|---|---|" + "---|" * len(shown))
    for name, (ref, fr) in data.items():
        loaded = [figure(noisy(fr[list(DIRECTIONS).index(d) * len(MAGNITUDES) + 3], ref, TARE_FRAMES).mean(axis=0))
                  for d in shown]
        print(f"| {name} | {figure(noisy(ref, ref, TARE_FRAMES).mean(axis=0)):.1f} | "
              + " | ".join(f"{x:.1f}" for x in loaded) + " |")

    print("\n## 2. a first tare under the load, then the load removed: the smallest load (N) whose first tare is "
          "dropped (every larger one is too); '-': none up to 20 N\n")
    print("| direction | " + " | ".join(DEVICES) + " |")
    print("|---|" + "---|" * len(DEVICES))
    smallest = {d: [] for d in DIRECTIONS}
    latency, worst_true = [], {}
    with tempfile.TemporaryDirectory() as tmp:
        tare_file = Path(tmp) / "tare.csv"
        for name, (ref, fr) in data.items():
            for k, d in enumerate(DIRECTIONS):
                caught = []
                for j in range(len(MAGNITUDES)):
                    frames = np.vstack([noisy(fr[k * len(MAGNITUDES) + j], ref, TARE_FRAMES + 100), noisy(ref, ref, 200)])
                    dropped, _ = run_stream(pipe, frames, tare_file)
                    caught.append(dropped is not None)
                    if dropped is not None:
                        latency.append(dropped - (TARE_FRAMES + 100) + 1)
                first = next((i for i in range(len(MAGNITUDES)) if all(caught[i:])), None)
                smallest[d].append("-" if first is None else f"{MAGNITUDES[first]:g}"
                                   + ("" if any(caught[:first]) is False else " (some smaller too)"))
            # a true first tare (unloaded), then every load of the device in turn, 50 frames each, unloaded between
            seq = [noisy(ref, ref, TARE_FRAMES + 20)] + [np.vstack([noisy(v, ref, 50), noisy(ref, ref, 20)]) for v in fr]
            dropped, forces = run_stream(pipe, np.vstack(seq), tare_file)
            fz = forces[TARE_FRAMES:, 2]
            held = np.convolve(fz, np.ones(PULL_FRAMES) / PULL_FRAMES, "valid")
            worst_true[name] = (dropped, float(np.nanmax(held)))
    for d, cells in smallest.items():
        print(f"| {d} | " + " | ".join(cells) + " |")
    print(f"\nDropped {min(latency)}-{max(latency)} unloaded frames after the load went (at least {PULL_FRAMES}).\n")
    print("## 3. true first tares (taken unloaded), then the 32 loads above, 50 frames each, unloaded between\n")
    for name, (dropped, fz) in worst_true.items():
        kept = "kept" if dropped is None else f"DROPPED at frame {dropped}"
        print(f"- {name}: {kept}; the largest Fz over {PULL_FRAMES} frames {fz:+.2f} N (a pull is > 0; limit "
              f"{PULL_MIN_N:g} N)")
    print(f"\n# {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
