"""Make the shipped calibration example (docs/calibration.md#a-worked-example): a rosbag2 and a
frames/forces CSV pair of a hand-made device under 12 known loads in 3D.

    .venv/bin/python examples/calibration/make_example.py

The device is scenes/devices/cuboid_joint_device_a.yaml (another rubber batch, contact impedance
2 x nominal, electrodes placed by hand), simulated honestly (its own mesh, seeded mismatch, 60 dB
noise, a rubber without creep: cstomo_sensor.model.simulate.VoltageSource); the models calibrated
against it are the nominal cuboid_joint's. Written here:

- ``bag/``: ``/cstomo_sensor/raw_voltages`` (sensor_msgs/Image 32FC1, as the node publishes them,
  stamped when measured, 10 frames/s) and ``/ft/wrench`` (geometry_msgs/WrenchStamped of a reference
  force/torque sensor at 50/s, its own stamps 4 ms off the frames', 0.02 N noise): 1.5 s unloaded,
  then each load held 0.6 s, then unloaded again;
- ``reference.csv`` (8 unloaded frames), ``frames.csv`` (2 frames of each load, other noise draws)
  and ``forces.csv`` (the known force of each frame, by ``frame``).
"""
from __future__ import annotations

import io
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent.parent
DEVICE = ROOT / "scenes" / "devices" / "cuboid_joint_device_a.yaml"
FRAME_RATE, WRENCH_RATE = 10.0, 50.0
REST, HOLD, END = 1.5, 0.6, 0.5  # s: unloaded first, each load, unloaded at the end
T0_NS = 1_700_000_000 * 10**9
WRENCH_OFFSET_NS = 4_000_000  # the reference sensor's clock ticks 4 ms after the board's
RECEIVE_DELAY_NS = 3_000_000  # the recorder receives each message 3 ms after its stamp
FT_NOISE = 0.02  # N, the reference sensor's per-axis noise
#: (magnitude N, elevation deg, azimuth deg) of the loads: 8..35 N, 25..90 deg, azimuths all round.
LOADS = [(20, 90, 0), (10, 60, 0), (25, 45, 90), (15, 30, 180), (30, 60, 270), (12, 25, 45), (35, 75, 135),
         (18, 40, 225), (8, 55, 315), (28, 35, 20), (22, 80, 200), (16, 50, 110)]


def _frames_csv(path: Path, frames: np.ndarray, comment: str) -> None:
    """A frames file (docs/formats.md#frames-file) with 7 significant digits (60 dB noise needs 4)."""
    buf = io.StringIO()
    buf.write(f"# {comment}\n")
    np.savetxt(buf, frames, delimiter=",", fmt="%.6e")
    path.write_text(buf.getvalue())


def main() -> int:
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from cstomo_sensor.angles import force_from_angles
    from cstomo_sensor.frames_io import write_forces
    from cstomo_sensor.model.simulate import VoltageSource
    from cstomo_sensor.ros.messages import OutputMessages, RawVoltagesCdr

    forces = np.array([force_from_angles(m, np.radians(el), np.radians(az)) for m, el, az in LOADS])
    times = np.concatenate([[0.0], REST + HOLD * np.arange(len(LOADS)), [REST + HOLD * len(LOADS)]])
    script_forces = np.vstack([np.zeros(3), forces, np.zeros(3)])
    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "load.csv"
        np.savetxt(script, np.column_stack([times, script_forces]), delimiter=",", header="time,fx,fy,fz",
                   comments="", fmt="%.6f")
        src = VoltageSource.from_args(sensor=str(DEVICE), load_script=str(script), snr_db=60.0, seed=7)
    rng = np.random.default_rng(7)
    duration = times[-1] + END
    # the bag: the node's stamped raw frames and the reference sensor's wrench
    bag = HERE / "bag"
    if bag.exists():
        shutil.rmtree(bag)
    store = get_typestore(getattr(Stores, "ROS2_KILTED", Stores.LATEST))
    raw = RawVoltagesCdr()
    wrench = OutputMessages(np.zeros((1, 3)), "cstomo_socket")
    t_frames = np.arange(int(round(duration * FRAME_RATE))) / FRAME_RATE
    t_wrench = np.arange(int(round(duration * WRENCH_RATE))) / WRENCH_RATE + WRENCH_OFFSET_NS * 1e-9
    messages = []
    for t in t_frames:
        stamp = T0_NS + int(round(t * 1e9))
        messages.append((stamp + RECEIVE_DELAY_NS, "raw", raw(src.frame(t, rng), stamp)))
    for t in t_wrench:
        stamp = T0_NS + int(round(t * 1e9))
        f = src.truth(t) + rng.normal(0.0, FT_NOISE, 3)
        messages.append((stamp + RECEIVE_DELAY_NS, "ft", wrench.wrench(f, stamp)))
    with Writer(bag, version=9) as w:
        conns = {"raw": w.add_connection("/cstomo_sensor/raw_voltages", "sensor_msgs/msg/Image", typestore=store),
                 "ft": w.add_connection("/ft/wrench", "geometry_msgs/msg/WrenchStamped", typestore=store)}
        for t_ns, which, data in sorted(messages, key=lambda m: m[0]):
            w.write(conns[which], t_ns, data)
    # the CSV pair: unloaded frames as the reference, two frames of each load, their known forces
    _frames_csv(HERE / "reference.csv", np.array([src.frame(0.0, rng) for _ in range(8)]),
                "8 unloaded frames of cuboid_joint_device_a (honest simulation, 60 dB; make_example.py)")
    mid = times[1:-1] + HOLD / 2  # the middle of each load
    _frames_csv(HERE / "frames.csv", np.array([src.frame(t, rng) for t in np.repeat(mid, 2)]),
                "2 frames of each of 12 loads of cuboid_joint_device_a (honest simulation, 60 dB; make_example.py)")
    write_forces(HERE / "forces.csv", np.repeat(forces, 2, axis=0))
    size = sum(f.stat().st_size for f in HERE.rglob("*") if f.is_file() and f.suffix != ".py")
    print(f"{len(t_frames)} frames and {len(t_wrench)} wrenches -> {bag}; reference.csv, frames.csv, forces.csv "
          f"({size / 1024:.0f} kB in all)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
