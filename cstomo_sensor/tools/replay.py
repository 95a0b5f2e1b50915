"""``cstomo replay``: run a recorded rosbag2 of raw voltages through the node's frame stream offline.

Reads every message of the topic ending in ``raw_voltages`` (sensor_msgs/Image 32FC1 as the node
publishes it, or the std_msgs/Float32MultiArray of older recordings; sqlite3 or mcap storage; NaN
marks a measurement the board flagged) with the ``rosbags``
library and writes a new bag with the node's output topics under the same namespace as the input
topic, with the same message types and the same numbers the live node publishes: both push the
frames through a :class:`~cstomo_sensor.frame_path.stream.FrameStream` in the one frame loop
(:func:`cstomo_sensor.frame_path.loop.run`: a :class:`~cstomo_sensor.ros.sources.BagSource` in, a
:class:`~cstomo_sensor.ros.sinks.BagWriter` and the forces file out) and build the messages with
:class:`~cstomo_sensor.ros.messages.OutputMessages`; the topics are the stream's outputs for the
settings given (``wrench_filtered`` with a filter, the stress fields with ``--stress-field-every``).

Tare: with ``reference`` (a frames file, e.g. the node's saved ``tare_<sensor>-<digest>.csv``) that frame
(the mean of its rows; their spread, or the saved ``.noise.csv`` beside it, is the noise; without
either, the noise is estimated from the bag's frames as they come, as the node does: force/reference/noise_estimate.py) is the
reference, if it is a plausible frame of this sensor (the node's rule for a saved tare); a file that records
when it was saved (the node's saved tare), before the bag's first frame, is a restart: its age at that frame
widens the slow states as the node's restart does (force/reference/files.py ``tare_age``); without it,
the first ``tare_frames`` frames of the bag are averaged into the reference and give no output,
exactly as the node in topic mode with ``tare_on_start: true``. Stamps: each output carries its input
frame's own stamp (the time it was measured), as the node stamps it; a legacy frame without one, the
bag's receive time. The filtered wrench runs on those stamps.

Nothing is left behind when the command fails: the bag is written in a temporary directory beside
``--out`` and moved into place (its files named after ``--out``) only when it and the forces file are
complete.
"""
from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import tempfile
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from ..errors import ConfigError, CstomoError
from ..force.reference.files import read_reference, tare_age
from ..force.slow_states.learned import read_directions
from ..frame_path.config import PipelineConfig, StreamConfig
from ..frame_path.loop import Results, run
from ..frame_path.outputs import RAW_TOPIC
from ..frame_path.pipeline import Pipeline
from ..frame_path.stream import FrameStream
from ..ros.sinks import BagWriter
from ..ros.sources import BagSource
from ..settings import default
from .common import ToolParser, add_creep_arg, add_pipeline_args, add_setting_arg, bag_typestore, help_text, pipeline_config, setup_logging

STORAGES = ("sqlite3", "mcap")
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReplaySummary:
    """What a replay did: input frames, results written, frames dropped as malformed, topics, and
    frames rejected as implausible (no output for them, as the node publishes none), results flagged
    as a foreign load (written all the same, as the node publishes them)."""

    frames_in: int
    results: int
    corrupt: int
    input_topic: str
    output_topics: tuple[str, ...]
    implausible: int = 0
    foreign_load: int = 0


def replay(in_bag: str | Path, out_bag: str | Path, config: PipelineConfig, *, reference: str | Path | None = None,
           topic: str | None = None, storage: str = "sqlite3", pipeline=None, progress=None,
           forces_file: str | Path | None = None, overwrite: bool = False, **stream) -> ReplaySummary:
    """Replay ``in_bag`` into a new bag ``out_bag`` (must not exist, unless ``overwrite``: an existing
    rosbag2 there is replaced once the replay is complete).

    Parameters
    ----------
    config : PipelineConfig
        The reconstruction settings (as the node's parameters give them).
    reference : path or None
        Frames file whose mean is the reference (several rows: their spread is the noise); None tares on the first ``tare_frames`` frames.
    **stream
        The frame stream's settings by name, as the node's parameters (:class:`StreamConfig`:
        ``tare_frames``, ``stress_field_every``: ``stress_field`` (and ``scene_stress_field``) for every
        N-th result, 0 = never, the default here; ``wrench_filter_hz``, ``drift_tracking``,
        ``creep_per_decade``, ``frame_id`` of the outputs, ...); the others as
        :meth:`StreamConfig.offline` makes them.
    pipeline : Pipeline or None
        An already built pipeline for ``config`` (its reference and mask are reset here).
    storage : {'sqlite3', 'mcap'}
        Storage plugin of the output bag.
    forces_file : path or None
        Also write the results as a forces file (docs/formats.md#forces-file) with the ``valid``,
        ``consistency`` and ``foreign_load`` columns, one row per processed frame.
    """
    from rosbags.rosbag2 import StoragePlugin, Writer  # optional: the [full] extra

    if storage not in STORAGES:
        raise ConfigError(f"{storage=}: expected one of {list(STORAGES)}")
    out_bag = Path(out_bag)
    if out_bag.exists() and not overwrite:
        raise ConfigError(f"output bag {out_bag}: exists; expected a new directory (--force replaces it)")
    if out_bag.exists() and not (out_bag / "metadata.yaml").is_file():  # never delete what is not a bag
        raise ConfigError(f"output bag {out_bag}: exists and is not a rosbag2 directory (no metadata.yaml); "
                          "not replaced, give a new directory")
    if out_bag.exists() and out_bag.resolve() == Path(in_bag).resolve():
        raise ConfigError(f"output bag {out_bag}: is the input bag; give another directory")
    if not out_bag.parent.is_dir():
        raise ConfigError(f"output bag {out_bag}: its directory {out_bag.parent} does not exist")
    if forces_file is not None and not Path(forces_file).parent.is_dir():
        raise ConfigError(f"forces file {forces_file}: its directory {Path(forces_file).parent} does not exist")
    had_forces = forces_file is not None and Path(forces_file).exists()
    stream_cfg = StreamConfig.offline(**stream)
    source = BagSource(in_bag, topic)  # the inputs are checked before any model is loaded
    try:
        pipe = pipeline if pipeline is not None else Pipeline.build(config, progress=progress)
        pipe.set_bad_channels(np.zeros(pipe.n_meas, bool))
        stream = FrameStream(pipe, stream_cfg)
        if reference is not None:  # a saved tare: the node's restart, its age taken at the bag's first frame
            first = source.peek()
            age = None if first is None else tare_age(reference, first.stamp_ns * 1e-9, file_time=False)
            stream.set_reference(*read_reference(reference, pipe.n_meas), f"reference {reference}", age_s=age,
                                 directions=read_directions(reference, pipe.n_meas))  # the device's own (force/slow_states/learned.py)
            log.info("reference %s: %s", reference, "a tare just taken (it records no time before the bag's first frame)"
                     if age is None else f"a saved tare {age:.0f} s old at the bag's first frame: the node's restart")
        else:
            stream.start_tare()
        prefix = source.topic[: -len(RAW_TOPIC)]
        names = stream.outputs
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        work = Path(tempfile.mkdtemp(prefix=f".{out_bag.name}.partial", dir=out_bag.parent))  # moved when complete
        partial = work / out_bag.name  # the bag's files are named after its directory
        try:
            with Writer(partial, version=9, storage_plugin=plugin) as writer:
                bag = BagWriter(writer, names, prefix, pipe.centers, stream_cfg.frame_id, bag_typestore())
                results = Results(path=forces_file)
                run(source, stream, [bag, results])
            n_in = source.messages
            corrupt = stream.counter.counts.corrupt + stream.counter.counts.rejected
            if n_in and corrupt == n_in:
                raise ConfigError(f"{in_bag}: none of the {n_in} messages of {source.topic} could be read as frames; "
                                  "no output written")
            if stream.tares.pending:  # no reference ever: no result, not an empty bag and exit 0
                raise ConfigError(f"{in_bag}: the bag ended during the tare ({n_in} frames, none taken as the "
                                  f"reference: the tare needs {stream_cfg.tare_frames} steady unloaded frames); give --reference "
                                  "FILE (unloaded frames of this device), fewer --tare-frames (at most the unloaded "
                                  "frames it starts with) or a bag that starts unloaded for longer; no output written")
            if overwrite and out_bag.exists():
                shutil.rmtree(out_bag)
            os.replace(partial, out_bag)
        except BaseException:
            if forces_file is not None and not had_forces:  # written at the run's end: only a complete replay leaves it
                Path(forces_file).unlink(missing_ok=True)
            raise
        finally:
            shutil.rmtree(work, ignore_errors=True)
    finally:
        source.close()
    return ReplaySummary(n_in, bag.results, corrupt, source.topic, tuple(prefix + n for n in names), stream.counter.counts.implausible,
                         sum(r.foreign_load for r in results.results))


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo replay", description=help_text(__doc__.split("\n\n")[0]))
    p.add_argument("in_bag", help="rosbag2 directory (sqlite3 or mcap) holding a */raw_voltages topic")
    p.add_argument("--out", required=True, metavar="DIR", help="output bag directory (must not exist, unless --force)")
    p.add_argument("--force", action="store_true", help="replace an existing output bag (once the replay is complete)")
    p.add_argument("--topic", help="input topic (default: the one ending in raw_voltages)")
    add_pipeline_args(p)
    p.add_argument("--reference", metavar="FILE", help="frames file used as the reference; a saved tare older than "
                   "the bag: the node's restart at its age (else: tare on the first frames)")
    add_setting_arg(p, "tare_frames")
    add_setting_arg(p, "stress_field_every", default=StreamConfig.offline().stress_field_every,
                    note=f"here no stress fields unless asked (the node's default: {default('stress_field_every')})")
    add_setting_arg(p, "wrench_filter_hz")
    add_setting_arg(p, "drift_tracking")
    add_creep_arg(p)
    add_setting_arg(p, "frame_id")
    p.add_argument("--storage", default="sqlite3", choices=list(STORAGES), help="output storage")
    p.add_argument("--forces", metavar="FILE", help="also write a forces file (CSV) with the consistency and foreign_load columns")
    return p


def main(argv: list[str] | None = None) -> int:
    """``cstomo replay IN_BAG --out OUT_BAG [...]``; prints a one-line summary."""
    args = parser().parse_args(argv)
    from rosbags.rosbag2 import ReaderError, WriterError  # optional: the [full] extra

    setup_logging(verbose=True, fmt="%(message)s")
    try:
        cfg = pipeline_config(args)
        stream = {f.name: getattr(args, f.name) for f in fields(StreamConfig) if hasattr(args, f.name)}  # its flags
        s = replay(args.in_bag, args.out, cfg, reference=args.reference, topic=args.topic, storage=args.storage,
                   forces_file=args.forces, overwrite=args.force,
                   progress=lambda m: print(f"model: {m}", file=sys.stderr), **stream)
    except (CstomoError, OSError, ReaderError, WriterError) as err:
        print(f"cstomo replay: error: {err}", file=sys.stderr)
        return 2
    print(f"{s.frames_in} frames from {s.input_topic}: {s.results} results written to {args.out} "
          f"({', '.join(s.output_topics)}); {s.corrupt} corrupt; {s.implausible} implausible; "
          f"{s.foreign_load} foreign load")
    return 0


if __name__ == "__main__":
    sys.exit(main())
