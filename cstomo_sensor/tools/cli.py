"""The ``cstomo`` command line: every thing the node does, without ROS.

Subcommands: ``model build``, ``model voltages``, ``reconstruct``, ``simulate``, ``estimate``,
``calibrate``, ``board-sim``, ``board-check``, ``replay``, ``demo``, ``bench``, ``bench-node``, ``render``,
``plot``, ``record``.
"""
from __future__ import annotations

import argparse
import resource
import signal
import sys
import time
from importlib import import_module

import numpy as np

from ..errors import ConfigError, CstomoError
from ..frames_io import atomic_write, check_out_file, read_frames, write_frames
from ..model.geometry import load_sensor
from ..settings import DEFAULT_SENSOR
from . import common
from .common import MAX_REPEATS, ToolParser, add_creep_arg, add_pipeline_args, add_setting_arg, pipeline_config, positive, setup_logging

#: Subcommands with a parser of their own: name -> module (relative to this package) with ``main(argv)``.
OWN_PARSERS = {"board-sim": ".board_sim", "board-check": ".board_check", "replay": ".replay",
               "calibrate": ".calibrate", "demo": ".demo", "bench-node": ".bench.node", "bench": ".bench.main",
               "render": ".render", "plot": ".plot", "record": ".record"}


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# The commands import the model, the inverse and the frame path when they run: ``cstomo --help`` and
# a command's --help load none of it.


def cmd_model_build(a) -> int:
    from ..model.cem import ForwardModel
    from ..model.mesh import MeshSpec, build_mesh

    g = load_sensor(a.sensor)
    t = time.perf_counter()
    mesh = build_mesh(g, MeshSpec(h=pipeline_config(a).mesh_size), a.cache_dir or None)
    t_mesh = time.perf_counter() - t
    fm = ForwardModel(g, mesh)
    sol = fm.solve()
    t = time.perf_counter()
    fm.jacobian(solution=sol)
    t_jac = time.perf_counter() - t
    s = mesh.summary()
    print(f"sensor {g.name}: mesh h = {a.mesh_size * 1e3:.2f} mm ({'cached' if mesh.info.get('cache_hit') else 'built'})")
    print(f"  nodes {s['nodes']}, cells {s['cells']}, volume {s['volume_m3'] * 1e9:.1f} mm^3 "
          f"(body {g.volume * 1e9:.1f}), min quality {s['min_quality']:.3f}")
    areas = np.array([p.area for p in fm.patches]) / (np.pi * np.array([e.radius for e in g.electrodes]) ** 2)
    tris = [p.n_triangles for p in fm.patches]
    print(f"  electrode patch area / disc area: {areas.min():.4f} .. {areas.max():.4f}; "
          f"triangles per electrode {min(tris)} .. {max(tris)}")
    print(f"  seconds: mesh {t_mesh:.3f}, assembly {fm.seconds['assembly']:.3f}, factorisation "
          f"{sol.seconds['factorisation']:.3f}, 16 solves {sol.seconds['solves']:.3f}, jacobian {t_jac:.3f}")
    v = sol.voltages
    print(f"  unloaded voltages at {g.drive_current * 1e3:.1f} mA: {v.min():.5f} .. {v.max():.5f} V "
          f"(|V| from {np.abs(v).min():.5f} V)")
    print(f"  peak memory {_peak_mb():.0f} MB")
    return 0


def cmd_model_voltages(a) -> int:
    from ..model.cem import ForwardModel
    from ..model.mesh import MeshSpec, build_mesh

    g = load_sensor(a.sensor)
    fm = ForwardModel(g, build_mesh(g, MeshSpec(h=pipeline_config(a).mesh_size), a.cache_dir or None))
    write_frames(a.out, fm.voltages()[None], comment=f"model prediction, {g.name}, unloaded, h={a.mesh_size:g} m")
    print(f"wrote {a.out}")
    return 0


def cmd_reconstruct(a) -> int:
    from ..inverse.reconstruction import build_model

    cfg = pipeline_config(a)
    g = load_sensor(cfg.sensor)
    ref = read_frames(a.reference)  # the inputs are checked before any model is built
    frames = read_frames(a.frames)
    model = build_model(g, cfg.recon_spec, cfg.cache_dir or None)
    dsigma = model.reconstruct(frames, ref.mean(axis=0))
    out = a.out if a.out.endswith(".npz") else a.out + ".npz"  # as np.savez names it
    with atomic_write(out) as f:
        np.savez(f, centers=model.centers, volumes=model.volumes, conductivity_change=dsigma)
    print(f"wrote {out}: {len(frames)} frames x {model.n_cells} cells (k = {model.iterations})")
    return 0


def cmd_estimate(a) -> int:
    from ..force.reference.files import read_reference
    from ..force.reference.noise_estimate import MIN_PAIRS, is_time_series, noise_level
    from ..force.slow_states.learned import read_directions
    from ..frame_path.config import StreamConfig
    from ..frame_path.loop import Results, run
    from ..frame_path.pipeline import Pipeline
    from ..frame_path.sources import ArraySource
    from ..frame_path.stream import FrameStream

    cfg = pipeline_config(a)
    if not a.rate > 0:
        raise ConfigError.bad_value("--rate", a.rate, "frames per second > 0")
    if a.reference_age is not None and not 0.0 <= a.reference_age < float("inf"):
        raise ConfigError.bad_value("--reference-age", a.reference_age, "seconds >= 0 (how old the saved tare is)")
    load_sensor(cfg.sensor)
    ref, noise, n_ref = read_reference(a.reference)  # the inputs are checked before any model is built
    directions = read_directions(a.reference)  # the device's own directions saved beside it (force/slow_states/learned.py)
    frames = read_frames(a.frames)
    creep = a.creep_per_decade
    _, pairs, agree = noise_level(frames)
    if creep and not is_time_series(pairs, agree):  # creep acts on a history in time
        why = (f"{pairs} consecutive frame pairs, fewer than {MIN_PAIRS}" if pairs < MIN_PAIRS else
               f"only {agree:.0%} of its {pairs} consecutive frame pairs differ by noise alone")
        print(f"creep: not compensated: {a.frames} does not look like one recording in time ({why}: frames of "
              "distinct loads?)", file=sys.stderr)
        creep = 0.0
    pipe = Pipeline.build(cfg)
    stream = FrameStream(pipe, StreamConfig.offline(wrench_filter_hz=0.0,  # the node's frame path
                                                    drift_tracking=a.drift_tracking, creep_per_decade=creep))
    message = stream.set_reference(ref, noise, n_ref, f"reference {a.reference}", age_s=a.reference_age,  # the node's restart
                                   directions=directions)
    noise_text = stream.estimate_noise(frames, a.frames)  # a one-frame reference: the noise from the frames
    print(f"reference: {n_ref} frame(s), noise {'measured' if noise is not None else noise_text}; "
          f"{'WARNING: ' if pipe.scale_report.warn else ''}{message}", file=sys.stderr)
    cal = pipe.calibration
    print(f"calibration: {cal.path} ({cal.accuracy})" if cal else "calibration: none (the nominal model)", file=sys.stderr)
    # frames in file order, a.rate per second (the drift tracker's clock), one row each (a frame without
    # a force: implausible); the optional valid column (docs/formats.md#forces-file) is written when a
    # frame was rejected as implausible; without it, every row holds a force
    rows = Results(stream, every_frame=True, path=a.out, valid_column="auto")
    run(ArraySource(frames, rate_hz=a.rate), stream, [rows])
    results, valid = rows.results, rows.valid
    bad = [i for i, r in enumerate(results) if not r.valid]
    for i in bad[:MAX_REPEATS]:  # the first few by name, the rest counted (the file's valid column has each)
        print(f"frame {i}: implausible ({results[i].reason}): no force", file=sys.stderr)
    if len(bad) > MAX_REPEATS:
        print(f"... and {len(bad) - MAX_REPEATS} more implausible frames (valid 0 in {a.out})", file=sys.stderr)
    foreign = sum(r.foreign_load for r in results)
    print(f"wrote {a.out}: {valid.sum()} forces ({a.estimator} estimator); {(~valid).sum()} implausible"
          + (f"; {foreign} with a foreign load (not on the socket)" if foreign else ""))
    return 0


def cmd_simulate(a) -> int:
    from ..model.simulate import simulate_scene_files
    from ..model.timeline import is_timeline_scene, simulate_timeline_files

    simulate = simulate_timeline_files if is_timeline_scene(a.scene) else simulate_scene_files
    simulate(a.scene, a.out, cache_dir=a.cache_dir or None)
    print(f"wrote {a.out}/reference.csv, frames.csv, truth.csv")
    return 0


def simulate_help() -> str:
    """``cstomo simulate --help``: the scene file's keys (the table: docs/formats.md#scene-file), with
    the defaults of :class:`~cstomo_sensor.model.simulate.Scene` (imported here: when the help is asked for)."""
    from ..model.simulate import Scene

    return f"""\
Frames of an honestly simulated device (docs/physics.md#honest-simulation): the truth on an independent
mesh, electrodes and contact impedances mismatched (seeded), white noise. Writes, under --out,
reference.csv (the unloaded frame), frames.csv (frames_per_load frames per load, in order) and
truth.csv (each frame's force in N, wrench frame; 0 for loads that are not socket or patch forces).

scene file (docs/formats.md#scene-file; a YAML mapping, only `loads` (or `timeline`) required, other keys refused):
  sensor               preset name or sensor YAML path (relative: to the scene file)
                       (default {DEFAULT_SENSOR})
  snr_db               noise, dB below the reference's rms; null for none (default {Scene.snr_db:g})
  seed                 seed of the mismatch and of the noise (default {Scene.seed})
  truth_mesh_size      m, the truth's independent mesh (default {Scene.truth_mesh_size:g})
  mechanics_mesh_size  m, the mesh of the mechanics of a force (default {Scene.mechanics_mesh_size:g})
  mismatch             contact_impedance: +- fraction per electrode (default {Scene.z_rel:g});
                       electrode_jitter: m, at most, within the face (default {Scene.jitter:g})
  frames_per_load      noisy frames per load (default {Scene.frames_per_load})
  loads                a list; each item is one of
      socket: {{force: [fx, fy, fz]}}  or  {{magnitude: N, elevation_deg: D, azimuth_deg: D (default 0)}}
      patches: [{{shape: square, size: m | shape: circle, radius: m, center: [u, v] m (default [0, 0]),
                 face: top (default), +x, -x, +y or -y}}], total_force: N (uniform normal pressure;
                 center in the face's own coordinates: (x, y) on top, (y, z) on +-x, (x, z) on +-y)
      inclusion: {{center: [x, y, z] m, radius: m, contrast: relative conductivity change}} (no mechanics)
  timeline             instead of loads: a device over time (temperature, drive, contact drift, creep,
                       contact tasks; docs/formats.md#timeline); frames.csv then holds a frame every
                       1/rate_hz s and truth.csv adds a time column and the true device state
"""


FRAMES_HELP = "frames file: 208 comma-separated volts a line (docs/formats.md#frames-file; `cstomo simulate` writes one)"


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``cstomo`` (the subcommands of :data:`OWN_PARSERS` parse their own arguments)."""
    p = ToolParser(prog="cstomo", description="The force sensor's tools without ROS; to see it work, start "
                                "with `cstomo demo` (README.md, docs/). Each command's --help says what it reads and writes.")
    p.add_argument("-v", "--verbose", action="store_true", help="log what the library does (INFO)")
    sub = p.add_subparsers(dest="cmd", required=True)
    model = sub.add_parser("model", help="forward model").add_subparsers(dest="what", required=True)
    b = model.add_parser("build", help="build (or load) the forward model and print a summary")
    v = model.add_parser("voltages", help="write the model's predicted unloaded frame")
    v.add_argument("--out", required=True, help="frames file to write (CSV, one line of 208 volts)")
    r = sub.add_parser("reconstruct", help="per-cell conductivity change for each frame (npz)")
    r.add_argument("--reference", required=True, help="frames file of unloaded frames (their mean is the reference)")
    r.add_argument("--frames", required=True, help=FRAMES_HELP)
    r.add_argument("--out", required=True, help="npz file to write")
    e = sub.add_parser("estimate", help="force vector for each frame (forces CSV)")
    e.add_argument("--reference", required=True,
                   help="frames file of unloaded frames (several: mean and noise; one without its .noise.csv: "
                        "the noise is estimated from the --frames file, a time series of the board)")
    e.add_argument("--reference-age", type=float, metavar="SECONDS",
                   help="the reference is a saved tare this old: the node's restart (default: a tare just taken)")
    e.add_argument("--frames", required=True, help=FRAMES_HELP)
    e.add_argument("--out", required=True, help="forces file to write (CSV, docs/formats.md#forces-file)")
    e.add_argument("--rate", type=positive("frames per second > 0"), default=100.0, metavar="HZ",
                   help="frames per second of the frames file, in file order: the clock of the drift tracking "
                        "(default %(default)g)")
    add_setting_arg(e, "drift_tracking")
    add_creep_arg(e)
    for q in (b, v, r):
        add_pipeline_args(q, estimator=False)
    add_pipeline_args(e)
    s = sub.add_parser("simulate", help="honestly simulated frames of a scene file", description=simulate_help)
    s.add_argument("--scene", required=True, metavar="FILE",
                   help="scene YAML file (keys above; examples in scenes/, e.g. cuboid_planar_60db.yaml)")
    s.add_argument("--out", required=True, metavar="DIR",
                   help="output directory, created if missing: reference.csv, frames.csv, truth.csv")
    add_setting_arg(s, "cache_dir")
    sub.add_parser("board-sim", help="simulated board on a pseudo-terminal (see cstomo board-sim -h)")
    sub.add_parser("board-check", help="identify a board, report its rate, gaps and noise (see cstomo board-check -h)")
    sub.add_parser("replay", help="rosbag2 raw_voltages -> node outputs (see cstomo replay -h)")
    sub.add_parser("calibrate", help="device calibration from known loads (see cstomo calibrate -h)")
    sub.add_parser("demo", help="the simulated board and the node together, live force estimates")
    sub.add_parser("bench-node", help="latency, CPU and memory of the real node on the simulated board "
                   "(see cstomo bench-node -h)")
    sub.add_parser("bench", help="speed and accuracy of every knob on honest scenes (see cstomo bench -h)")
    sub.add_parser("render", help="off-screen pictures of mesh, stress and image (see cstomo render -h)")
    sub.add_parser("plot", help="forces over time, estimated beside true, as a PNG (see cstomo plot -h)")
    sub.add_parser("record", help="the live node's topics to a rosbag2 (see cstomo record -h)")
    return p


def subcommand_parser(argv: list[str]) -> tuple[argparse.ArgumentParser, list[str]]:
    """(the parser that parses ``cstomo ARGV``'s options, the arguments after its subcommand words):
    ``["model", "build", "--sensor", "disc"]`` gives ``cstomo model build``'s parser and ``["--sensor",
    "disc"]``. Raises :class:`ConfigError` for a subcommand that does not exist."""
    argv = list(argv)
    if argv and argv[0] in OWN_PARSERS:
        return import_module(OWN_PARSERS[argv[0]], __package__).parser(), argv[1:]
    p = build_parser()
    while True:
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs:
            return p, argv
        if not argv or argv[0] not in subs[0].choices:
            given = repr(argv[0]) if argv else "nothing"
            raise ConfigError(f"{p.prog}: {given} is no subcommand; expected one of {sorted(subs[0].choices)}")
        p = subs[0].choices[argv.pop(0)]


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the `cstomo` process: once its command is done it only exits, and a late SIGINT
        # must not turn that clean exit into a death by SIGINT (ros2 launch not run from a terminal sends
        # its own SIGINT to each process it started, after the group's Ctrl-C: board-sim's exit takes
        # ~0.1 s, then launch said "process has died [exit code -2]"); a command that handles SIGINT
        # itself (board-sim) leaves it ignored once it stops, not restored first (common.restore_signals)
        common.SIGINT_AFTER_COMMAND = signal.SIG_IGN
        code = main(sys.argv[1:])
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        return code
    argv = list(argv)
    if argv and argv[0] in OWN_PARSERS:  # commands that own their argument parsing
        return import_module(OWN_PARSERS[argv[0]], __package__).main(argv[1:])
    a = build_parser().parse_args(argv)
    setup_logging(a.verbose)
    handlers = {("model", "build"): cmd_model_build, ("model", "voltages"): cmd_model_voltages}
    fn = handlers.get((a.cmd, getattr(a, "what", None))) or {
        "reconstruct": cmd_reconstruct, "estimate": cmd_estimate, "simulate": cmd_simulate}[a.cmd]
    try:
        if fn is not cmd_simulate and getattr(a, "out", None):  # simulate's --out is a directory it makes
            check_out_file(a.out)
        return fn(a)
    except (CstomoError, OSError) as err:
        print(f"cstomo {a.cmd}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
