"""``cstomo board-sim``: the simulated board (:class:`~cstomo_sensor.board.sim.SimulatedBoard`) on a
pseudo-terminal, playing a scene or a load script of an honestly simulated device.

A load script's rubber creeps (``--creep``, default :data:`~cstomo_sensor.settings.TYPICAL_CREEP_PER_DECADE`,
the node's default compensation): the script is played as a :class:`~cstomo_sensor.model.timeline.Timeline`
of its loads with that creep and nothing else changing, over ``--duration`` (else the script's last
time plus :data:`SCRIPT_HOLD_S`; after that the device holds its last state: the last load no longer
creeps). ``--creep 0`` plays each load exactly (:class:`~cstomo_sensor.model.simulate.VoltageSource`).
"""
from __future__ import annotations

import argparse
import signal
import sys
import time

import numpy as np

from ..board.links import is_virtual
from ..board.sim import DEFAULT_RATE_HZ, FaultConfig, SimulatedBoard
from ..cache import on_miss
from ..errors import CstomoError
from ..frames_io import read_load_script
from ..model.geometry import DEFAULT_SNR_DB, load_sensor
from ..model.simulate import VoltageSource
from ..model.timeline import Timeline, TimelineSpec, is_timeline_scene
from ..settings import DEFAULT_SENSOR, MAX_LOAD, RATED_FORCE, TYPICAL_CREEP_PER_DECADE
from .common import ToolParser, add_setting_arg, positive, restore_signals, setup_logging

#: Seconds a load script's last load is simulated creeping when no ``--duration`` is given (the
#: board then runs until stopped, the last load held without further creep after this): an hour,
#: 4.6 decades from 0.1 s; the knots of an hour's hold cost about 5 s of solves once (cached).
SCRIPT_HOLD_S = 3600.0


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo board-sim", description="Simulated board on a pseudo-terminal.")
    add_setting_arg(p, "sensor")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--scene", metavar="FILE", help="scene YAML file: a timeline scene's rubber creeps as its timeline's creep: "
                                     "says; a scene's list of loads (foreign loads too) holds each load exactly, "
                                     "1 s each (--creep does not apply to scenes)")
    src.add_argument("--load-script", metavar="CSV", help=f"load script CSV (time,fx,fy,fz; socket forces up to {MAX_LOAD:g} N, "
                                           f"1.5 x the rated {RATED_FORCE:g} N); its rubber creeps (--creep)")
    p.add_argument("--creep", type=float, default=TYPICAL_CREEP_PER_DECADE, metavar="C",
                   help="the load script's rubber creep per decade of time from 0.1 s after each change of load "
                        "(default %(default)g: the typical rubber, the node's default creep_per_decade, so the "
                        "node with its defaults reads a held load constant; real rubbers 0.02..0.06; 0: a rubber "
                        "that does not creep, each load held exactly). The script is simulated as a timeline over "
                        f"--duration, else its last time + {SCRIPT_HOLD_S:g} s, after which the last load holds "
                        "without further creep; the first run solves its knots (about 40 ms each), cached")
    p.add_argument("--rate", type=positive("frames per second > 0"), default=DEFAULT_RATE_HZ, metavar="HZ",
                   help="frames per second")
    p.add_argument("--duration", type=positive("seconds > 0"), metavar="S",
                   help="seconds to run (default: until SIGINT/SIGTERM)")
    add_setting_arg(p, "protocol")
    p.add_argument("--link", metavar="PATH", help="symlink kept pointing at the current pty")
    p.add_argument("--snr", type=float, default=None, metavar="DB",
                   help=f"signal-to-noise ratio in dB (default: the scene's snr_db; {DEFAULT_SNR_DB:g} for a load script)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the noise and of the faults; with --load-script also of the simulated device's "
                   "mismatch (electrode places, contact impedances): another seed is another device, computed once")
    g = p.add_argument_group("faults (injected, for tests; off by default)")
    g.add_argument("--bit-flip", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--drop", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--truncate", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--garbage", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--garbage-bytes", type=int, default=48, metavar="N", help="bytes of each garbage burst")
    g.add_argument("--nan", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--stall-at", type=float, metavar="S", help="stop sending at this time (s from the start)")
    g.add_argument("--stall-for", type=float, default=0.0, metavar="S", help="for this long")
    g.add_argument("--disconnect-at", type=float, metavar="S", help="remove the pty at this time (s from the start)")
    g.add_argument("--reappear-after", type=float, default=0.5, metavar="S", help="and make a new one this much later")
    g.add_argument("--saturate-channel", type=int, metavar="I", help="value index 0..207")
    g.add_argument("--full-scale", type=float, default=2.5, metavar="V", help="the saturated channel's value")
    g.add_argument("--dead-electrode", type=int, metavar="E", help="electrode index 0..15")
    return p


#: The start of the line board-sim says before computing its loads' frames (``cstomo demo`` says it in its own words).
COMPUTING = "cstomo board-sim: computing the frames of"


def main(argv: list[str] | None = None) -> int:
    """``cstomo board-sim``: print ``device: PATH`` first, then stream until done or signalled."""
    p = parser()
    args = p.parse_args(argv)
    setup_logging()  # warnings, and the progress of a first run's solves on a terminal
    if is_virtual(args.link):
        p.error(f"--link {args.link}: a virtual link lives in one process, no other could open it; give a path")
    # SIGINT and SIGTERM while the loads are computed: stop quietly (SIGINT also when the parent
    # left it ignored, as a shell does for a background job)
    previous = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _main(args)
    except KeyboardInterrupt:
        print("cstomo board-sim: stopped before streaming", file=sys.stderr)
        return 0
    finally:
        restore_signals(previous)  # SIGINT stays ignored in the `cstomo` process (common.SIGINT_AFTER_COMMAND)


def _stopping() -> None:
    """board-sim begins stopping (signalled, or its board ended): further SIGINTs and SIGTERMs are ignored
    until :func:`main` returns, and in the `cstomo` process SIGINTs until it exits (common.restore_signals;
    ros2 launch sends its own SIGINT after the group's, at any moment of the exit). Ignored by a handler
    that does nothing, not ``SIG_IGN``: a signal that arrived just before is then handled by it too."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _ignore)


def _ignore(*_: object) -> None:
    """A signal while board-sim stops: nothing to do."""


def _interrupt(*_: object) -> None:
    _stopping()
    raise KeyboardInterrupt


def _main(args: argparse.Namespace) -> int:
    if not 0 <= args.creep < 1:  # NaN too; before the loads' frames are computed, not after
        print(f"cstomo board-sim: error: --creep {args.creep:g}: expected a fraction per decade, 0 <= C < 1 "
              "(rubbers: 0.02..0.06; 0: no creep)", file=sys.stderr)
        return 2
    try:
        faults = FaultConfig(
            bit_flip=args.bit_flip, drop=args.drop, truncate=args.truncate, garbage=args.garbage,
            garbage_bytes=args.garbage_bytes, nan=args.nan, stall_at=args.stall_at, stall_for=args.stall_for,
            disconnect_at=args.disconnect_at, reappear_after=args.reappear_after,
            saturate_channel=args.saturate_channel, full_scale=args.full_scale, dead_electrode=args.dead_electrode,
        )
        layers = load_sensor(args.sensor).layers
        # a bad script or scene is refused before the line below (reading them builds no mesh)
        if args.load_script:
            read_load_script(args.load_script, MAX_LOAD)
        timeline = None
        if args.scene and is_timeline_scene(args.scene):  # a device over time (docs/formats.md#timeline)
            timeline = Timeline.from_scene(args.scene, snr_db=args.snr)
        # a cold cache computes the loads' frames for tens of seconds before the pty exists: say so at
        # its first miss (a warm cache reads them in a fraction of a second: nothing to say)
        said = []

        def computing(_path) -> None:
            if not said:
                said.append(True)
                print(f"{COMPUTING} {args.scene or args.load_script} on the simulator's own "
                      "mesh (the first run of these inputs takes 20-60 s, later runs read them from the cache)",
                      file=sys.stderr, flush=True)

        with on_miss(computing):
            if timeline is not None:
                source = timeline.prepare()
            elif args.load_script and args.creep != 0:  # a creeping rubber: the script as a timeline
                source = script_timeline(args.load_script, args.creep, sensor=args.sensor, duration=args.duration,
                                         snr_db=args.snr, seed=args.seed)
            else:
                source = VoltageSource.from_args(
                    sensor=args.sensor, scene=args.scene, load_script=args.load_script, snr_db=args.snr, seed=args.seed
                )
        board = SimulatedBoard(
            source, protocol=args.protocol, rate_hz=args.rate, duration=args.duration, link=args.link,
            faults=faults, seed=args.seed, layers=layers,
        )
    except (CstomoError, OSError) as err:
        print(f"cstomo board-sim: error: {err}", file=sys.stderr)
        return 2

    def stop(*_: object) -> None:  # the first signal stops the board; board-sim ignores the next ones (_stopping)
        _stopping()
        board.stop()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, stop)
    print(f"device: {board.device}", flush=True)
    streaming = False
    try:
        board.start()
        while not board.join(0.1):  # the main thread stays free for the signal handlers
            if board.script_started.is_set() and not streaming:
                streaming = True
                # the load script's t = 0 (NodeWithBoard.wait_streaming), on the system clock (the node's
                # ROS clock, its wrenches' stamps): a frame of script time t is stamped about t0 + t
                t0 = time.time() - (time.monotonic() - board.script_start)
                print(f"streaming t0={t0:.6f}", flush=True)
    finally:
        _stopping()
        board.close()
    st = board.stats()
    for line in st.describe():
        print(line, file=sys.stderr)
    return 0


def script_timeline(load_script, creep: float = TYPICAL_CREEP_PER_DECADE, *, sensor: str = DEFAULT_SENSOR,
                    duration: float | None = None, snr_db: float | None = None, seed: int = 0,
                    cache_dir=None) -> Timeline:
    """A load script played by a rubber creeping by ``creep`` per decade (module docstring): a
    :class:`Timeline` of the script's loads and nothing else changing, over ``duration`` (else the
    last time + :data:`SCRIPT_HOLD_S`), its knots solved (or read from the cache) now. Noise at
    ``snr_db`` (None: :data:`DEFAULT_SNR_DB`, as a load script without creep)."""
    times, forces = read_load_script(load_script)
    last = float(times[-1]) if len(times) else 0.0
    spec = TimelineSpec(duration=float(duration) if duration is not None and duration > 0 else last + SCRIPT_HOLD_S,
                        creep=float(creep), load_times=tuple(np.asarray(times, float)),
                        load_forces=tuple(map(tuple, np.asarray(forces, float))))
    return Timeline(spec, sensor, snr_db=DEFAULT_SNR_DB if snr_db is None else snr_db, seed=seed,
                    cache_dir=cache_dir).prepare()
