"""``cstomo board-sim``: the simulated board (:class:`~cstomo_sensor.board.sim.SimulatedBoard`) on a
pseudo-terminal, playing a scene or a load script of an honestly simulated device."""
from __future__ import annotations

import argparse
import signal
import sys

from ..board.links import is_virtual
from ..board.sim import FaultConfig, SimulatedBoard
from ..errors import CstomoError
from ..model.geometry import DEFAULT_SNR_DB, load_sensor
from ..model.simulate import VoltageSource
from ..model.timeline import Timeline, is_timeline_scene


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cstomo board-sim", description="Simulated board on a pseudo-terminal.")
    p.add_argument("--sensor", required=True, help="sensor preset name or YAML path")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--scene", help="scene YAML file")
    src.add_argument("--load-script", help="load script CSV (time,fx,fy,fz)")
    p.add_argument("--rate", type=float, required=True, help="frames per second")
    p.add_argument("--duration", type=float, help="seconds to run (default: until SIGINT/SIGTERM)")
    p.add_argument("--protocol", default="binary", help="binary (default) or text")
    p.add_argument("--link", help="symlink kept pointing at the current pty")
    p.add_argument("--snr", type=float, default=None,
                   help=f"signal-to-noise ratio in dB (default: the scene's snr_db; {DEFAULT_SNR_DB:g} for a load script)")
    p.add_argument("--seed", type=int, default=0)
    g = p.add_argument_group("faults")
    g.add_argument("--bit-flip", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--drop", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--truncate", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--garbage", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--garbage-bytes", type=int, default=48, metavar="N")
    g.add_argument("--nan", type=float, default=0.0, metavar="P", help="probability per frame")
    g.add_argument("--stall-at", type=float, metavar="S")
    g.add_argument("--stall-for", type=float, default=0.0, metavar="S")
    g.add_argument("--disconnect-at", type=float, metavar="S")
    g.add_argument("--reappear-after", type=float, default=0.5, metavar="S")
    g.add_argument("--saturate-channel", type=int, metavar="I", help="value index 0..207")
    g.add_argument("--full-scale", type=float, default=2.5, metavar="V")
    g.add_argument("--dead-electrode", type=int, metavar="E", help="electrode index 0..15")
    return p


def main(argv: list[str] | None = None) -> int:
    """``cstomo board-sim``: print ``device: PATH`` first, then stream until done or signalled."""
    parser = _parser()
    args = parser.parse_args(argv)
    if is_virtual(args.link):
        parser.error(f"--link {args.link}: a virtual link lives in one process, no other could open it; give a path")
    # SIGINT and SIGTERM while the loads are computed: stop quietly (SIGINT also when the parent
    # left it ignored, as a shell does for a background job)
    previous = {sig: signal.signal(sig, _interrupt) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return _main(args)
    except KeyboardInterrupt:
        print("cstomo board-sim: stopped before streaming", file=sys.stderr)
        return 0
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _interrupt(*_: object) -> None:
    raise KeyboardInterrupt


def _main(args: argparse.Namespace) -> int:
    try:
        faults = FaultConfig(
            bit_flip=args.bit_flip, drop=args.drop, truncate=args.truncate, garbage=args.garbage,
            garbage_bytes=args.garbage_bytes, nan=args.nan, stall_at=args.stall_at, stall_for=args.stall_for,
            disconnect_at=args.disconnect_at, reappear_after=args.reappear_after,
            saturate_channel=args.saturate_channel, full_scale=args.full_scale, dead_electrode=args.dead_electrode,
        )
        layers = load_sensor(args.sensor).layers
        if args.scene and is_timeline_scene(args.scene):  # a device over time (docs/formats.md#timeline)
            source = Timeline.from_scene(args.scene, snr_db=args.snr).prepare()
        else:
            source = VoltageSource.from_args(
                sensor=args.sensor, scene=args.scene, load_script=args.load_script, snr_db=args.snr, seed=args.seed
            )
        board = SimulatedBoard(
            source, protocol=args.protocol, rate_hz=args.rate, duration=args.duration, link=args.link,
            faults=faults, seed=args.seed, layers=layers,
        )
    except (CstomoError, OSError) as err:
        print(f"cstomo board-sim: {err}", file=sys.stderr)
        return 2
    previous = {sig: signal.signal(sig, lambda *_: board.stop()) for sig in (signal.SIGINT, signal.SIGTERM)}
    print(f"device: {board.device}", flush=True)
    streaming = False
    try:
        board.start()
        while not board.join(0.1):  # the main thread stays free for the signal handlers
            if board.script_started.is_set() and not streaming:
                streaming = True
                print("streaming", flush=True)  # the load script's t = 0 (NodeWithBoard.wait_streaming)
    finally:
        board.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    st = board.stats()
    for line in st.describe():
        print(line, file=sys.stderr)
    return 0
