"""``cstomo calibrate``: fit a device calibration on known loads (docs/calibration.md).

From files (formats: docs/formats.md)::

    cstomo calibrate --sensor S --reference REF.csv --frames FRAMES.csv --forces FORCES.csv --out DEVICE.yaml

rows of the forces file matched to frames by ``frame`` (frames without a force row are not used;
extra columns are ignored). From a rosbag2 recording::

    cstomo calibrate --bag DIR --voltages-topic /cstomo_sensor/raw_voltages --wrench-topic /ft/wrench --out DEVICE.yaml

``raw_voltages`` (sensor_msgs/Image, as the node publishes them: stamped with the time each frame was
measured; a legacy Float32MultiArray recording is stamped by the bag's receive time) paired with the
reference sensor's geometry_msgs/WrenchStamped (its header stamp; the force already in the sensor's
wrench frame) nearest in time, within ``--stamp-tolerance`` (default 0.02 s), and only on the same
load plateau (the reference force steady within 0.3 N for 3 wrenches or more): frames without one,
or taken while the load changed, are not used. The recipe: docs/calibration.md. The reference: ``--reference``, else the paired frames under
less than ``--unloaded-below`` N. Writes DEVICE.yaml and, beside it, DEVICE.cv.csv, the cross-validated
accuracy before and after calibration, which it also prints.

The rubber's creep per decade goes into the file too, fitted on the recording's loads held 5 s or more
(3 at least; a bag's frames have their stamps, a frames file its ``--rate``; the rows of a forces file
under ``--unloaded-below`` N are its rests), else on ``--creep-hold``, else given by
``--creep-per-decade``; one line says which, or why none (docs/calibration.md#the-creep).

The device's own directions go into the file too: the whole recording in time order (a bag's frames with
their stamps; a frames file with ``--rate``) through the frame stream of the fitted calibration, from the
reference, as the node would run it; the directions its rests between the loads teach the drift tracker
(force/slow_states/learned.py) are saved as ``learned_directions``, and a stream of this calibration starts
with them. One line says how many, or why none (docs/calibration.md#the-devices-own-directions).
"""
from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import ConfigError, CstomoError
from ..force.reference.calibration import calibrate, reference_path_of
from ..force.reference.files import read_reference, reference_of, saved_at, write_reference
from ..force.slow_states.creep import HELD_FOR, MIN_HELD
from ..force.slow_states.learned import AVG, FIRST, Directions
from ..frame_path.pipeline import Pipeline
from ..frames_io import atomic_write, read_force_rows, read_frames
from .common import ToolParser, add_pipeline_args, help_text, pipeline_config, positive

STAMP_TOLERANCE = 0.02  # s
UNLOADED_BELOW = 0.5  # N
#: A load plateau of the reference wrench: its force stays within this many newtons (a reference
#: F/T sensor's noise is ~0.05 N; a hand-held or weight-stacked load settles within 0.2 N), for at
#: least this many wrenches.
PLATEAU_TOLERANCE = 0.3  # N
PLATEAU_MIN_SAMPLES = 3


def pair_by_stamp(t_frames: np.ndarray, t_wrench: np.ndarray, tolerance: float) -> tuple[np.ndarray, np.ndarray]:
    """(frame indices, wrench indices) of the frames with a wrench stamp within ``tolerance`` s (nearest)."""
    order = np.argsort(t_wrench)
    tw = t_wrench[order]
    j = np.clip(np.searchsorted(tw, t_frames), 1, max(len(tw) - 1, 1))
    left = np.maximum(j - 1, 0)
    pick = np.where(np.abs(tw[left] - t_frames) <= np.abs(tw[np.minimum(j, len(tw) - 1)] - t_frames), left,
                    np.minimum(j, len(tw) - 1))
    ok = np.abs(tw[pick] - t_frames) <= tolerance
    return np.flatnonzero(ok), order[pick[ok]]


def plateaus(t_wrench: np.ndarray, forces: np.ndarray, tolerance: float = PLATEAU_TOLERANCE,
             min_samples: int = PLATEAU_MIN_SAMPLES) -> np.ndarray:
    """The plateau of each reference wrench (in stamp order): runs of wrenches whose force stays within
    ``tolerance`` N of the run's first one, of at least ``min_samples`` wrenches, numbered from 0;
    -1 for a wrench of a load change (a run too short: the load was moving)."""
    order = np.argsort(t_wrench)
    f = forces[order]
    label = np.full(len(f), -1)
    start, n = 0, 0
    for i in range(1, len(f) + 1):
        if i == len(f) or np.linalg.norm(f[i] - f[start]) > tolerance:
            if i - start >= min_samples:
                label[start:i] = n
                n += 1
            start = i
    out = np.empty_like(label)
    out[order] = label
    return out


def pair_on_plateaus(t_frames: np.ndarray, t_wrench: np.ndarray, forces: np.ndarray, tolerance: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """(frame indices, wrench indices): each frame with the nearest wrench within ``tolerance`` s, kept
    only when the frame's stamp lies inside that wrench's plateau, half a wrench period in from its
    first and its last wrench (the load may change anywhere between two wrenches): a frame is never
    paired across a load change, nor with a load that was moving."""
    i, j = pair_by_stamp(t_frames, t_wrench, tolerance)
    label = plateaus(t_wrench, forces)
    ok = label[j] >= 0
    n = label.max() + 1 if len(label) else 0
    first = np.full(n, np.inf)
    last = np.full(n, -np.inf)
    np.minimum.at(first, label[label >= 0], t_wrench[label >= 0])
    np.maximum.at(last, label[label >= 0], t_wrench[label >= 0])
    lab = np.where(ok, label[j], 0)
    guard = 0.5 * float(np.median(np.diff(np.sort(t_wrench)))) if len(t_wrench) > 1 else 0.0
    ok &= (t_frames[i] >= first[lab] + guard) & (t_frames[i] <= last[lab] - guard)
    return i[ok], j[ok]


def read_bag(path: str | Path, voltages_topic: str, wrench_topic: str, tolerance: float = STAMP_TOLERANCE,
             timing: bool = False):
    """(frames (n, 208), forces (n, 3), frames read, wrenches read) of a rosbag2 recording: frames
    paired with the reference wrench on the same load plateau (:func:`pair_on_plateaus`), by the
    frame's own stamp (the node's stamped raw frames; the bag's receive time for a legacy
    Float32MultiArray recording) and the wrench's header stamp. ``timing``: a fifth item, the
    :class:`HeldLoads` of the pairs (their stamps, plateaus and the plateaus' starts: the creep's fit)."""
    from geometry_msgs.msg import WrenchStamped
    from rclpy.serialization import deserialize_message
    from rosbags.rosbag2 import Reader
    from sensor_msgs.msg import Image
    from std_msgs.msg import Float32MultiArray

    from ..ros.messages import LEGACY_RAW_TYPE, frame_from_raw_msg
    from ..ros.sources import bag_path

    frames, tf, forces, tw = [], [], [], []
    with Reader(bag_path(path)) as reader:
        topics = {c.topic for c in reader.connections}
        for t in (voltages_topic, wrench_topic):
            if t not in topics:
                raise ConfigError(f"topic {t!r}: not in the bag {path}; it holds {sorted(topics)}")
        conns = [c for c in reader.connections if c.topic in (voltages_topic, wrench_topic)]
        legacy = any(c.msgtype == LEGACY_RAW_TYPE for c in conns if c.topic == voltages_topic)
        for conn, t_ns, raw in reader.messages(connections=conns):
            if conn.topic == voltages_topic:
                values, flagged, stamp = frame_from_raw_msg(
                    deserialize_message(bytes(raw), Float32MultiArray if legacy else Image))
                if flagged is not None:
                    continue  # a measurement the board flagged: not a calibration frame
                frames.append(values)
                tf.append((stamp or t_ns) * 1e-9)
            else:
                m = deserialize_message(bytes(raw), WrenchStamped)
                forces.append((m.wrench.force.x, m.wrench.force.y, m.wrench.force.z))
                tw.append(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9)
    if not frames or not forces:
        raise ConfigError(f"bag {path}: {len(frames)} messages on {voltages_topic}, {len(forces)} on {wrench_topic}; "
                          "expected both")
    tw, forces = np.array(tw), np.array(forces)
    i, j = pair_on_plateaus(np.array(tf), tw, forces, tolerance)
    out = np.array(frames)[i], forces[j], len(frames), len(forces)
    if not timing:
        return out
    label = plateaus(tw, forces)
    order = np.argsort(tw)
    return (*out, HeldLoads(np.array(tf)[i], label[j], plateau_starts(tw[order], label[order])),
            Recording(np.array(frames), np.array(tf), i))


@dataclass
class HeldLoads:
    """When the frames of a calibration recording were measured (``times``, s, in time order), the
    held load (plateau) each is on (``load``, numbered in time order; -1 none) and when each load was
    applied (``starts``, s): what the creep's fit needs (force/slow_states/creep.py fit_creep_loads)."""

    times: np.ndarray
    load: np.ndarray
    starts: np.ndarray


@dataclass
class Recording:
    """The whole calibration recording: every frame (``frames`` (n, n_meas) volts), when it was measured
    (``times``, s; any order) and which are the paired ones (``paired``: their indices, in the order of the
    pairs); ``rest``: the frames known to be unloaded (their reference force under ``--unloaded-below``): what the
    device's own directions are learned from (:func:`recording_directions`)."""

    frames: np.ndarray
    times: np.ndarray
    paired: np.ndarray
    rest: np.ndarray | None = None

    def rests(self, unloaded: np.ndarray) -> Recording:
        """This recording with ``rest`` the paired frames ``unloaded`` (bool, one per pair)."""
        rest = np.zeros(len(self.frames), bool)
        rest[np.asarray(self.paired)[np.asarray(unloaded, bool)]] = True
        return replace(self, rest=rest)


def plateau_starts(t: np.ndarray, label: np.ndarray) -> np.ndarray:
    """When each plateau's load was applied: midway between the previous plateau's last sample and its
    own first (the load changed in between; the first plateau: its first sample). ``t`` in time order,
    ``label`` numbered from 0 in time order (-1: none)."""
    n = label.max() + 1 if len(label) else 0
    first, last = np.full(n, np.inf), np.full(n, -np.inf)
    on = label >= 0
    np.minimum.at(first, label[on], t[on])
    np.maximum.at(last, label[on], t[on])
    return np.concatenate([first[:1], 0.5 * (last[:-1] + first[1:])]) if n else first


def file_loads(idx: np.ndarray, forces: np.ndarray, rate: float) -> HeldLoads:
    """:class:`HeldLoads` of a forces file's rows (frame numbers ``idx``, in any order) of a frames file
    recorded at ``rate`` frames/s: a plateau is a run of consecutive frames whose force stays within
    :data:`PLATEAU_TOLERANCE` of the run's first (the frames left out of the forces file: the changes)."""
    order = np.argsort(idx, kind="stable")
    k, f = idx[order], forces[order]
    label = np.empty(len(k), int)
    n, start = -1, 0
    for i in range(len(k)):
        if i == 0 or k[i] != k[i - 1] + 1 or np.linalg.norm(f[i] - f[start]) > PLATEAU_TOLERANCE:
            n, start = n + 1, i
        label[i] = n
    t = k / rate
    out = np.empty(len(k), int)
    out[order] = label
    return HeldLoads(idx / rate, out, plateau_starts(t, label))


#: The end of ``cstomo calibrate --help``: the two ways to run it; the rest is docs/calibration.md.
EPILOG = """\
from files:  cstomo calibrate --reference REF.csv --frames FRAMES.csv --forces FORCES.csv --out DEVICE.yaml
from a bag:  cstomo calibrate --bag DIR --wrench-topic /ft/wrench --out DEVICE.yaml
Writes DEVICE.yaml and DEVICE.cv.csv (the cross-validated accuracy before and after, also printed).
How to record the loads, the pairing of frames with wrenches, the creep: docs/calibration.md."""


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo calibrate", description=help_text(__doc__.splitlines()[0]), epilog=EPILOG)
    add_pipeline_args(p)
    p.add_argument("--reference", metavar="FILE", help="frames file of unloaded frames (required with --frames)")
    p.add_argument("--frames", metavar="FILE", help="frames file of the loaded frames")
    p.add_argument("--forces", metavar="FILE", help="forces file: the known force of each used frame (by 'frame')")
    p.add_argument("--bag", metavar="DIR", help="rosbag2 directory instead of --frames/--forces")
    p.add_argument("--voltages-topic", default="/cstomo_sensor/raw_voltages", metavar="TOPIC",
                   help="the raw frames topic in --bag (sensor_msgs/Image, as the node publishes ~/raw_voltages)")
    p.add_argument("--wrench-topic", metavar="TOPIC", help="the reference sensor's WrenchStamped topic (with --bag)")
    p.add_argument("--stamp-tolerance", type=positive("seconds > 0"), default=STAMP_TOLERANCE, metavar="S",
                   help="largest stamp difference of a frame and its wrench (default %(default)g s)")
    p.add_argument("--unloaded-below", type=positive("newtons >= 0", zero=True), default=UNLOADED_BELOW, metavar="N",
                   help="with --bag and no --reference: frames under this force are the reference; with --frames: "
                        "rows of the forces file under it are rests, the creep's history, not loads (default %(default)g)")
    p.add_argument("--rate", type=positive("frames per second > 0"), metavar="HZ",
                   help="frames per second of --frames when it is one recording in time order: its loads held "
                        f"{HELD_FOR:g} s or more give the creep (a bag's frames carry their stamps)")
    p.add_argument("--creep-per-decade", type=float, metavar="C",
                   help="the rubber's creep per decade, written into the file (default: fitted with --creep-hold, "
                        f"else on the recording's loads held {HELD_FOR:g} s or more, {MIN_HELD} at least; else none: "
                        "the node's creep_per_decade applies)")
    p.add_argument("--creep-hold", metavar="FRAMES",
                   help="frames file of one load held still for a minute or more, its first frame when the load "
                        "was applied: the creep per decade is fitted from it")
    p.add_argument("--creep-rate", type=positive("frames per second > 0"), default=100.0, metavar="HZ",
                   help="frames per second of --creep-hold (default %(default)g)")
    p.add_argument("--out", required=True, metavar="FILE", help="calibration file to write (YAML); the table goes beside it")
    return p


def recorded_noise(frames: np.ndarray, ref: np.ndarray) -> np.ndarray | None:
    """The per-channel noise (volts, one level for all) of a recording's consecutive frames, by the
    stream's rules (force/reference/noise_estimate.py), or None (the estimators assume 60 dB) when its frame pairs do not
    differ by noise alone; prints which."""
    from ..force.reference.files import DEFAULT_NOISE_DB, NOISE_DB_RANGE
    from ..force.reference.noise_estimate import is_time_series, noise_level, snr_db

    level, pairs, agree = noise_level(frames)
    db = snr_db(level, ref) if level == level else float("nan")
    if is_time_series(pairs, agree) and NOISE_DB_RANGE[0] <= db <= NOISE_DB_RANGE[1]:
        print(f"noise: estimated from {pairs} consecutive frame pairs ({db:.1f} dB): the reference has one frame")
        return np.full(len(ref), level)
    print(f"noise: assumed {DEFAULT_NOISE_DB:g} dB: the reference has one frame and {agree:.0%} of the "
          f"{pairs} consecutive frame pairs differ by noise alone (record the reference's frames, or hold "
          "each load for several frames)")
    return None


def held_creep(pipe, frames: np.ndarray, rate: float) -> float:
    """The creep per decade of a held load's frames (the first when the load was applied, ``rate``
    frames/s): their force magnitudes through the stream, neither creep nor drift compensated."""
    from ..force.slow_states.creep import fit_creep
    from ..frame_path.config import StreamConfig
    from ..frame_path.loop import Results, run
    from ..frame_path.sources import ArraySource
    from ..frame_path.stream import FrameStream

    if not rate > 0:
        raise ConfigError.bad_value("--creep-rate", rate, "frames per second > 0")
    stream = FrameStream(pipe, StreamConfig.offline(wrench_filter_hz=0.0, drift_tracking=False,
                                                    creep_per_decade=0.0, noise_estimation=False))
    rows = Results(stream, every_frame=True)
    run(ArraySource(frames, rate_hz=rate, start_s=1.0), stream, [rows])
    mags = np.array([r.magnitude if r.valid else np.nan for r in rows.results])
    try:
        return fit_creep(np.arange(len(frames)) / rate + 1.0 / rate, mags)
    except ValueError as err:
        raise ConfigError(f"--creep-hold: {err}") from None


def recording_creep(pipe, frames: np.ndarray, loads: HeldLoads | None, why_not: str = "") -> tuple[float | None, str]:
    """(creep per decade or None, the line that says so) fitted on a calibration recording's held loads
    (:class:`HeldLoads` of ``frames``; None: ``why_not``): their uncompensated forces through the
    pipeline (its reference set), force/slow_states/creep.py fit_creep_loads."""
    from ..force.slow_states.creep import fit_creep_loads

    if loads is not None:
        order = np.argsort(loads.times, kind="stable")
        est = np.array([pipe.process(v, with_field=False, gate=False).force for v in frames[order]])
        try:
            c, n = fit_creep_loads(loads.times[order], est, loads.load[order], loads.starts)
            return c, f"creep: {c:.2%} per decade, fitted on the {n} loads (or rests) of the recording held {HELD_FOR:g} s or more"
        except ValueError as err:
            why_not = str(err)
    return None, (f"creep: not fitted from the recording ({why_not}): the node's creep_per_decade applies "
                  "(hold loads longer, or give --creep-hold or --creep-per-decade)")


def recording_directions(pipe, reference: tuple, recording: Recording | None, why_not: str = ""
                         ) -> tuple[Directions | None, str, str]:
    """(the device's own directions or None, the note for the file, the line that says so) learned from a
    calibration ``recording`` (None: ``why_not``): its frames in time order through the frame stream of ``pipe``
    (its calibration set: the node's stream of this calibration, the calibration's creep) from ``reference`` (the
    reference, its noise and its frame count), its drift tracker learning from the rests between the loads
    (force/slow_states/learned.py): each frame known to be unloaded (``recording.rest``) feeds it
    whatever the rest test says (:meth:`~cstomo_sensor.force.slow_states.coordinator.SlowStates.known_unloaded`), so a
    change whose phantom force keeps the rest test from counting them is learned too."""
    from ..frame_path.config import StreamConfig
    from ..frame_path.stream import FrameStream

    if recording is None:
        return None, "", f"directions: not learned from the recording ({why_not})"
    order = np.argsort(recording.times, kind="stable")
    stamps = np.round(np.asarray(recording.times, float)[order] * 1e9).astype(np.int64)
    stream = FrameStream(pipe, StreamConfig.offline(wrench_filter_hz=0.0))
    stream.set_reference(*reference, source="the calibration's reference")
    rest = np.zeros(len(order), bool) if recording.rest is None else np.asarray(recording.rest, bool)[order]
    for values, stamp, known in zip(recording.frames[order], stamps.tolist(), rest.tolist()):
        stream.slow.known_unloaded(known)
        stream.push(values, stamp_ns=stamp)
    learner, found = stream.slow.learner, stream.slow.directions
    fed = learner.fed if learner is not None else 0
    note = (f"learned by cstomo calibrate from {fed} clear frames of its recording of {len(order)} "
            f"({learner.decisions if learner is not None else 0} decisions)")
    if learner is not None and not learner.decisions:
        return None, "", (f"directions: none learned: the recording's {fed} clear frames (of {len(order)}: its rests) "
                          f"are too few to decide ({FIRST * AVG} needed: record longer rests between the loads)")
    if not len(found):
        return None, "", (f"directions: none learned from the recording's {fed} clear frames (of {len(order)}: its "
                          "rests): over it the device changed as the model's states say, or less than its rests' noise")
    return found, note, (f"directions: {len(found)} of the device's own learned from the recording's {fed} clear frames "
                         f"(of {len(order)}: its rests), saved in the calibration: a stream of it tracks them from its "
                         "first frame")


def run(a) -> int:
    from ..force.slow_states.creep import creep_problem

    cfg = pipeline_config(a)
    if a.creep_per_decade is not None and a.creep_hold:
        raise ConfigError("give --creep-per-decade or --creep-hold, not both")
    if a.creep_per_decade is not None and creep_problem(a.creep_per_decade):
        raise ConfigError.bad_value("--creep-per-decade", a.creep_per_decade, creep_problem(a.creep_per_decade))
    if a.creep_hold and not a.creep_rate > 0:
        raise ConfigError.bad_value("--creep-rate", a.creep_rate, "frames per second > 0")
    if a.rate is not None and not a.rate > 0:
        raise ConfigError.bad_value("--rate", a.rate, "frames per second > 0")
    if a.rate is not None and a.bag:
        raise ConfigError("--rate is for --frames files; a bag's frames carry their own stamps (give no --rate)")
    hold = read_frames(a.creep_hold) if a.creep_hold else None  # read before the model is built
    if cfg.calibration_file:
        raise ConfigError("--calibration: calibrate against the nominal model (give no --calibration)")
    t0 = time.perf_counter()
    if a.bag:
        if a.frames or a.forces:
            raise ConfigError("--bag reads the frames and the forces from the bag: give no --frames/--forces")
        if not a.wrench_topic:
            raise ConfigError("--bag needs --wrench-topic: the reference sensor's WrenchStamped topic in the bag "
                              f"(frames from --voltages-topic, default {a.voltages_topic})")
        frames, forces, n_v, n_w, loads, whole = read_bag(a.bag, a.voltages_topic, a.wrench_topic, a.stamp_tolerance,
                                                          timing=True)
        recording, why_not = frames, ""
        source = {"bag": str(a.bag), "voltages_topic": a.voltages_topic, "wrench_topic": a.wrench_topic,
                  "stamp_tolerance_s": a.stamp_tolerance}
        print(f"bag: {len(frames)} of {n_v} frames paired with one of {n_w} wrenches within {a.stamp_tolerance:g} s")
        unloaded = np.linalg.norm(forces, axis=1) < a.unloaded_below
        if a.reference:
            ref, noise, n_ref = read_reference(a.reference)
        elif unloaded.sum() >= 1:
            ref, noise = reference_of(frames[unloaded])
            n_ref = int(unloaded.sum())
            recorded = float(np.max(loads.times[unloaded]))  # the bag's stamps: when the device was unloaded
            source["reference"] = f"{int(unloaded.sum())} paired frames under {a.unloaded_below:g} N"
        else:
            raise ConfigError(f"no --reference and no paired frame under {a.unloaded_below:g} N to tare on")
        frames, forces = frames[~unloaded], forces[~unloaded]
        whole = whole.rests(unloaded)
    else:
        if not (a.reference and a.frames and a.forces):
            raise ConfigError("give --reference, --frames and --forces (or --bag with its topics)")
        ref, noise, n_ref = read_reference(a.reference)
        all_frames = read_frames(a.frames)
        idx, forces = read_force_rows(a.forces)
        if len(idx) and idx.max() >= len(all_frames):
            raise ConfigError.bad_value("frame", int(idx.max()), f"a frame of {a.frames} (0..{len(all_frames) - 1})")
        recording, loads = all_frames[idx], None if a.rate is None else file_loads(idx, forces, a.rate)
        why_not = "a frames file has no time: give --rate, its frames per second, when it is one recording in time order"
        load = np.linalg.norm(forces, axis=1) >= a.unloaded_below  # rows below: rests (the creep's history)
        whole = None if a.rate is None else Recording(all_frames, (np.arange(len(all_frames)) + 1) / a.rate, idx).rests(~load)
        frames, forces = recording[load], forces[load]
        source = {"frames": str(a.frames), "forces": str(a.forces)}
    if a.reference:
        source["reference"] = str(a.reference)
        recorded = saved_at(a.reference) or Path(a.reference).stat().st_mtime  # as a saved tare's age is read
    if noise is None:  # a one-frame reference: the noise from the recording, as the node estimates it
        noise = recorded_noise(all_frames if not a.bag else frames, ref)
    pipe = Pipeline.build(cfg, progress=lambda m: print(f"model: {m}", file=sys.stderr))
    report = pipe.set_reference(ref, noise, n_ref)
    print(f"reference: {report.message}")
    creep = a.creep_per_decade
    if creep is not None:
        print(f"creep: {creep:.2%} per decade, as given (--creep-per-decade)")
    elif hold is not None:
        creep = held_creep(pipe, hold, a.creep_rate)
        print(f"creep: {creep:.2%} per decade, fitted on the held load of {a.creep_hold}")
    else:
        creep, line = recording_creep(pipe, recording, loads, why_not)
        print(line)
    cal = calibrate(pipe, frames, forces, fitted_on=source)
    if creep is not None:
        cal = replace(cal, creep_per_decade=float(creep))
    # the device's own directions: the recording through the stream of this calibration (recording_directions)
    pipe.set_calibration(cal)
    directions, note, line = recording_directions(pipe, (ref, noise, n_ref), whole, why_not)
    print(line)
    cal = replace(cal, directions=directions, directions_note=note)
    out = Path(a.out)
    cal.save(out)
    # the device's unloaded reference beside it: a first start without a saved tare starts from it
    write_reference(reference_path_of(out), ref, noise, frames=n_ref,
                    comment=f"cstomo_sensor unloaded reference of the calibration {out.name}: mean of {n_ref} frames, "
                            f"{time.strftime('%Y-%m-%dT%H:%M:%S%z', time.localtime(recorded))}")
    table = cv_table(cal)
    with atomic_write(out.with_suffix(".cv.csv")) as f:
        f.write(table.encode())
    b, c = cal.cv["before"], cal.cv["after"]
    print(f"{cal.cv['loads']} loads, {cal.cv['frames']} frames; cross-validated ({cal.cv['method']}, "
          f"{cal.estimator} estimator):")
    print("               angle deg med/p90   magnitude % med/p90")
    for name, s in (("uncalibrated", b), ("calibrated", c)):
        if s is None:
            print(f"  {name:12s}  not cross-validated: every fold leaves fewer than 3 loads in 3 directions")
            continue
        print(f"  {name:12s}  {s['angle_deg_median']:7.2f} / {s['angle_deg_p90']:6.2f}    "
              f"{s['magnitude_pct_median']:7.2f} / {s['magnitude_pct_p90']:6.2f}")
    print(f"wrote {out}, {out.with_suffix('.cv.csv')} and {reference_path_of(out)} (the unloaded reference: "
          f"a node started without a saved tare starts from it) in {time.perf_counter() - t0:.1f} s")
    return 0


def cv_table(cal) -> str:
    """The cross-validated accuracy as CSV (one row before, one after)."""
    keys = ["angle_deg_median", "angle_deg_p90", "magnitude_pct_median", "magnitude_pct_p90"]
    lines = ["calibration,estimator,method,loads,frames," + ",".join(keys)]
    for name in ("before", "after"):
        s = cal.cv[name] or dict.fromkeys(keys, float("nan"))
        lines.append(f"{name},{cal.estimator},{cal.cv['method']},{cal.cv['loads']},{cal.cv['frames']}," +
                     ",".join(f"{s[k]:g}" for k in keys))
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(argv)
    try:
        return run(a)
    except (CstomoError, OSError) as err:
        print(f"cstomo calibrate: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
