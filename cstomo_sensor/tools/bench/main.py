"""``cstomo bench``: the speed/accuracy table (:mod:`.table`), held-out forces and the sigma's nominal error
by direction (:mod:`.heldout`), GREIT figures (:mod:`.greit`), the filtered wrench (:mod:`.filter`), the pyEIT
comparison (:mod:`.pyeit`), the weight rule (:mod:`.weight`), the calibration effort (:mod:`.effort`), the
scene field with the foreign-load flag (:mod:`.scene`), the zero over time and the per-frame cost through the
stream (:mod:`.drift`), what a robot does to them on devices outside the model (:mod:`.robot`)."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

from ..common import ToolParser, add_setting_arg, positive, setup_logging
from .drift import drift_bench, frame_cost
from .effort import calibration_effort
from .filter import filter_bench
from .greit import greit
from .heldout import heldout, one_frame_reference, sigma_table
from .pyeit import run as run_pyeit
from .robot_change import robot_bench
from .scene import run_scene
from .table import run
from .weight import choose_weight


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo bench", description=(
        "Speed and accuracy on honest simulations (docs/benchmark.md): by default the table of every knob; "
        "one of the options below runs one other benchmark instead."))
    g = p.add_mutually_exclusive_group()
    g.add_argument("--smoke", action="store_true", help="default setting only, 2 scenes (under a minute, warm caches)")
    g.add_argument("--quick", action="store_true", help="every knob, 8 scenes (a few minutes)")
    g.add_argument("--pyeit", action="store_true", help="comparison with pyEIT (needs `pip install pyeit`)")
    g.add_argument("--heldout", type=positive("a whole number >= 1", kind=int), metavar="N",
                   help="both estimators on N held-out forces at 60 and 40 dB")
    g.add_argument("--greit", action="store_true", help="GREIT-style figures for inclusions at several places")
    g.add_argument("--calibration-effort", action="store_true",
                   help="held-out accuracy of a simulated non-nominal device against the number of calibration loads")
    g.add_argument("--filter", action="store_true", help="delay and noise reduction of ~/wrench_filtered at 60 and 40 dB")
    g.add_argument("--choose-weight", action="store_true",
                   help="the rule for the Landweber weight power p on the training-side scenes")
    g.add_argument("--drift", action="store_true",
                   help="the zero and the accuracy when the device changes after its tare, with and without tracking")
    g.add_argument("--frame-cost", action="store_true",
                   help="time per frame through the stream, both estimators, drift tracking off and on, side by side")
    g.add_argument("--sigma-table", type=int, metavar="N",
                   help="the nominal model's error by the load's direction (the sigma's calibration residual) on N loads")
    g.add_argument("--scene", action="store_true", help="scene stress field and foreign-load flag (accuracy, rates, cost)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--calibration", default="", metavar="FILE",
                   help="with --heldout: a device calibration (cstomo calibrate) applied to both estimators")
    p.add_argument("--one-frame-reference", action="store_true",
                   help="with --heldout: loads held 10 frames each through the frame stream, after a one-frame "
                        "reference with the noise assumed, given or estimated from the frames, and a 50-frame tare")
    p.add_argument("--robot", action="store_true",
                   help="with --drift: what a robot does (a device outside the model, loads back to back while it "
                        "warms, restarts from an old tare, the 30-minute warm-up) instead of the drift table")
    add_setting_arg(p, "cache_dir")
    return p


def main(argv: list[str] | None = None) -> int:
    p = parser()
    a = p.parse_args(sys.argv[1:] if argv is None else argv)
    setup_logging()
    if a.robot and not a.drift:
        p.error("--robot goes with --drift")
    if a.one_frame_reference and not a.heldout:
        p.error("--one-frame-reference goes with --heldout N")
    if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
        print("cstomo bench: note: OPENBLAS_NUM_THREADS is not 1; timings are pinned to one core anyway",
              file=sys.stderr)
    if a.pyeit:
        try:
            import pyeit  # noqa: F401  (optional; never a dependency of the package)
        except ImportError:
            return p.fail("--pyeit: pyEIT is not installed (pip install pyeit, in the activated .venv)")

        run_pyeit(a.out, a.cache_dir or None)
        return 0
    if a.choose_weight:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        choose_weight(a.out, a.cache_dir or None)
        return 0
    if a.calibration_effort:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        calibration_effort(a.out, cache_dir=a.cache_dir or None)
        return 0
    if a.sigma_table:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        sigma_table(a.sigma_table, a.out, a.cache_dir or None)
        return 0
    if a.scene:
        run_scene(a.out, a.cache_dir or None)
        return 0
    if a.drift and a.robot:
        robot_bench(a.out, a.cache_dir or None)
        return 0
    if a.drift:
        drift_bench(a.out, a.cache_dir or None)
        return 0
    if a.frame_cost:
        frame_cost(a.out, a.cache_dir or None)
        return 0
    if a.heldout or a.greit or a.filter:
        Path(a.out).mkdir(parents=True, exist_ok=True)
        study = one_frame_reference if a.one_frame_reference else heldout
        job = ((lambda o, c: study(a.heldout, o, c, calibration=a.calibration)) if a.heldout
               else filter_bench if a.filter else greit)
        job(a.out, a.cache_dir or None)
        return 0
    run("smoke" if a.smoke else "quick" if a.quick else "full", a.out, a.cache_dir or None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
