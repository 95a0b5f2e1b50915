"""Make the small rosbag2 of the replay tests: test/data/raw_voltages_bag (+ raw_voltages_truth.csv).

    .venv/bin/python test/data/make_bag.py

A simulated device (cstomo_sensor.model.simulate.VoltageSource: honest simulation, independent mesh,
mismatched electrodes, 60 dB noise, a rubber without creep: replay it with --creep-per-decade 0) follows
a load script: unloaded, then four socket forces, then
unloaded again; 50 frames per second for 4 s, recorded as the node records them
(std_msgs/Float32MultiArray on /cstomo_sensor/raw_voltages, as the node recorded them before its raw
frames carried a stamp: the bag tests replay's reading of older recordings; built by
cstomo_sensor.ros.messages.legacy_raw_voltages_msg).
"""
from __future__ import annotations

import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
BAG = HERE / "raw_voltages_bag"
TRUTH = HERE / "raw_voltages_truth.csv"
TOPIC = "/cstomo_sensor/raw_voltages"
RATE = 50.0
DURATION = 4.0
T0_NS = 1_700_000_000 * 10**9
SCRIPT = """time,fx,fy,fz
0.0,0,0,0
0.4,0,0,-20
1.4,10,0,-10
2.4,0,8,-25
3.4,0,0,0
"""


def main() -> int:
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    from cstomo_sensor.frames_io import write_forces
    from cstomo_sensor.model.simulate import VoltageSource
    from cstomo_sensor.ros.messages import LEGACY_RAW_TYPE, legacy_raw_voltages_msg

    with tempfile.TemporaryDirectory() as tmp:
        script = Path(tmp) / "load.csv"
        script.write_text(SCRIPT)
        src = VoltageSource.from_args(sensor="cuboid_joint", load_script=str(script), snr_db=60.0, seed=7)
    rng = np.random.default_rng(7)
    times = np.arange(int(DURATION * RATE)) / RATE
    frames = [src.frame(t, rng) for t in times]
    if BAG.exists():
        shutil.rmtree(BAG)
    store = get_typestore(getattr(Stores, "ROS2_KILTED", Stores.LATEST))
    with Writer(BAG, version=9) as w:
        conn = w.add_connection(TOPIC, LEGACY_RAW_TYPE, typestore=store)
        for t, v in zip(times, frames):
            w.write(conn, T0_NS + int(round(t * 1e9)), serialize_message(legacy_raw_voltages_msg(v)))
    write_forces(TRUTH, np.array([src.truth(t) for t in times]))
    size = sum(f.stat().st_size for f in BAG.rglob("*") if f.is_file())
    print(f"{len(frames)} frames -> {BAG} ({size / 1024:.0f} kB); truth -> {TRUTH}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
