"""Smoke tests of the command-line tools no other test runs: ``cstomo demo`` (node + simulated board,
a scripted load), ``cstomo bench --heldout`` and ``--greit`` on tiny settings, and the metre unit of
``--mesh-size``."""
from __future__ import annotations

import csv
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cstomo_sensor.inverse.reconstruction import ReconSpec
from cstomo_sensor.tools.cli import main as cstomo

#: The demo's short script: unloaded for 3 s (the node reaches the board up to 2 s after it appears
#: (reconnect backoff) and then tares on 50 frames; a tare across the load step is refused, and the next
#: one would be loaded), then 20 N straight down. `cstomo demo --load-script` on it, run to its end with
#: ``--hold 2.5``, is test_colcon_install.py's demo from the install (judged by :func:`check_demo_run`).
DEMO_SCRIPT = "time,fx,fy,fz\n0,0,0,0\n3,0,0,-20\n"


def check_demo_run(returncode: int, stdout: str, stderr: str) -> None:
    """A run of ``cstomo demo --load-script`` on :data:`DEMO_SCRIPT` to its end: exit 0, no traceback,
    lines of the 20 N load, a summary that says what each figure is (the simulated board's counts
    included) and a median angle error under 5 deg (20 N straight down, honest simulation at 60 dB)."""
    text = stdout + stderr
    assert returncode == 0, text
    assert "Traceback" not in text
    lines = [ln for ln in stdout.splitlines() if "script row 2" in ln and "20.00" in ln]
    assert lines, text
    summary = next(ln for ln in stdout.splitlines() if "median angle error" in ln)
    angle = float(summary.split("median angle error")[1].split("deg")[0])
    assert angle < 5.0, summary
    tail = stdout[stdout.index("\nsummary"):]
    first = next(ln for ln in tail.splitlines() if "first wrench" in ln)
    assert float(first.split()[2]) < 200, first
    assert "settled lines" in tail and "against the scripted true force" in tail, tail
    board = tail[tail.index("simulated board"):]
    assert "sent" in board and "frames whole and unharmed" in board and "injected {" not in text, board
    assert "computing" not in board, board  # board-sim's own 'computing' line: the demo's [1/3] said it
    if "overrun" in board:
        assert "nothing read it" in board, board


@pytest.fixture(scope="module")
def demo_load_solved():
    """The mechanics of :data:`DEMO_SCRIPT`'s 20 N on the simulated board's device (the default sensor's
    honest simulation), solved in this process: ``board-sim`` then reads it from the cache instead of
    factorising the elasticity in a process of its own (15-40 s on a fresh clone), and this worker keeps
    the factor for the next test's bench, whose held-out device is the same sensor's (conftest keeps the
    mechanics). board-sim's own computing on a cold cache is test_board_sim_says_it_computes_only_when_it_does'."""
    from cstomo_sensor.model.geometry import load_sensor
    from cstomo_sensor.model.simulate import Load, Truth

    Truth(load_sensor("cuboid_joint")).theta(Load("socket", force=(0.0, 0.0, -20.0)))


@pytest.mark.slow
def test_demo_interrupted_by_sigint_ends_quietly_with_its_summary(tmp_path, demo_load_solved):
    """Ctrl-C in the middle of a held load: exit 0, the summary, no traceback, and the node's wait
    for the board's link (which appears only after the board has computed its loads) logged once,
    not once per retry. With the linear estimator: what Ctrl-C does is the demo's, not an estimator's,
    and on a fresh clone its build is half the default's (no response set: the default estimator's is
    built once by the suite's in-process tests, not here in a process of its own); the default
    estimator's demo is judged to its end by test_colcon_install (check_demo_run)."""
    import signal
    import time

    pytest.importorskip("rclpy")
    script = tmp_path / "load.csv"
    script.write_text(DEMO_SCRIPT)
    exe = Path(sys.executable).parent / "cstomo"
    out, err = tmp_path / "out.txt", tmp_path / "err.txt"
    with open(out, "w") as fo, open(err, "w") as fe:
        p = subprocess.Popen([str(exe), "demo", "--load-script", str(script), "--hold", "120", "--rate", "100",
                              "--estimator", "linear", "--plot", str(tmp_path / "demo.png")],
                             stdout=fo, stderr=fe, text=True,
                             env=dict(os.environ, OPENBLAS_NUM_THREADS="1", TMPDIR=str(tmp_path)))
        try:
            deadline = time.monotonic() + 200
            # settled under the 20 N load (two lines of it), then Ctrl-C
            while sum("script row 2" in ln and "20.00" in ln for ln in out.read_text().splitlines()) < 4:
                assert p.poll() is None and time.monotonic() < deadline, out.read_text() + err.read_text()
                time.sleep(0.2)
            p.send_signal(signal.SIGINT)
            code = p.wait(30)
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
    text = out.read_text() + err.read_text()
    assert code == 0, text
    assert "Traceback" not in text and "Exception" not in text, text
    assert "stopped at t =" in text and "median angle error" in text, text
    opens = [ln for ln in text.splitlines() if "open failed" in ln]
    assert len(opens) <= 1, opens
    assert not list(tmp_path.glob("cstomo_demo_*"))  # its temporary files are removed
    # --plot: the run's picture, written after the summary, a PNG of the default size
    assert f"wrote {tmp_path / 'demo.png'}" in text, text
    head = (tmp_path / "demo.png").read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and int.from_bytes(head[16:20], "big") == 1200
    assert int.from_bytes(head[20:24], "big") == 800


def _rows(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


@pytest.mark.slow  # runs the bench on three forces (~50 s)
def test_bench_heldout_on_three_forces(tmp_path):
    assert cstomo(["bench", "--heldout", "3", "--out", str(tmp_path)]) == 0
    rows = _rows(tmp_path / "heldout.csv")
    assert {(r["snr_db"], r["estimator"]) for r in rows if r["subset"] == "all"} == {
        (s, e) for s in ("60.0", "40.0") for e in ("linear", "model")}
    for r in rows:
        if r["subset"] == "all" and r["snr_db"] == "60.0":
            assert float(r["angle_med"]) < 10.0 and float(r["mag_pct_med"]) < 20.0, r


@pytest.mark.slow
def test_bench_sigma_table_on_a_few_forces(tmp_path):
    """``cstomo bench --sigma-table N``: the nominal model's error by elevation on the training side's device
    and the held-out one, both estimators; each row's rms error is a relative error of a few % (the
    estimators' stated accuracy, docs/benchmark.md), and the one in use grows toward lateral loads."""
    assert cstomo(["bench", "--sigma-table", "3", "--out", str(tmp_path)]) == 0
    rows = _rows(tmp_path / "sigma_table.csv")
    assert {(r["device"], r["estimator"]) for r in rows} == {(d, e) for d in ("training", "held-out")
                                                             for e in ("model", "linear")}
    assert sum(int(r["n"]) for r in rows) == 4 * 3
    for r in rows:
        assert 0.0 < float(r["rms_pct"]) < 15.0 and 0.5 < float(r["in_use_pct"]) < 10.0, r
    used = {r["elevation"]: float(r["in_use_pct"]) for r in rows if r["estimator"] == "model"}
    assert list(used.values()) == sorted(used.values(), reverse=True)  # bins from 20 deg up: falls toward 90


@pytest.mark.slow
def test_bench_frame_cost_times_both_estimators_with_and_without_tracking(tmp_path):
    """``cstomo bench --frame-cost`` (one round here): a row per estimator and tracking, every frame of
    the stream timed, the host's load stated. No timing assertions."""
    from cstomo_sensor.settings import ESTIMATORS
    from cstomo_sensor.tools.bench.drift import frame_cost

    frame_cost(tmp_path, rounds=1, say=lambda msg: None)
    rows = _rows(tmp_path / "frame_cost.csv")
    assert [(r["estimator"], r["tracking"]) for r in rows] == [(e, t) for e in ESTIMATORS for t in ("False", "True")]
    for r in rows:
        assert int(r["frames"]) == 3100 and 0 < float(r["us_median"]) <= float(r["us_p90"]) and float(r["us_mean"]) > 0, r
        assert float(r["load_start"]) >= 0 and float(r["load_end"]) >= 0


def test_bench_greit_figures(tmp_path):
    assert cstomo(["bench", "--greit", "--out", str(tmp_path)]) == 0
    rows = _rows(tmp_path / "greit.csv")
    ours = [r for r in rows if r["imager"].startswith("ours")]
    after = f"p={ReconSpec.weight_power:g}"
    assert {r["imager"].split()[1] for r in ours} == {"p=0", after}  # before and after, 6 places each
    assert len(ours) == 12
    for r in ours:
        amp, pos = float(r["amplitude_response"]), float(r["position_error_mm"])
        assert math.isfinite(amp) and amp > 0 and pos < 20.0, r


def test_mesh_size_is_in_metres_everywhere(capsys):
    with pytest.raises(SystemExit) as done:  # millimetres refused by the parser, with the fix named
        cstomo(["model", "build", "--mesh-size", "4"])
    assert done.value.code == 2
    err = capsys.readouterr().err
    assert "--mesh-size" in err and "metres" in err and "0.004" in err


@pytest.mark.parametrize("argv,prog,names", [([], "cstomo", ["demo", "estimate", "record"]),
                                               (["model"], "cstomo model", ["build", "voltages"])])
def test_no_command_names_the_commands_expected_in_one_line(capsys, argv, prog, names):
    """Before: `cstomo: error: the following arguments are required: cmd` (`what` for `cstomo model`)."""
    with pytest.raises(SystemExit) as done:
        cstomo(argv)
    assert done.value.code == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"{prog}: error: no command given; expected one of ") and line.endswith(f"({prog} --help)")
    assert all(n in line for n in names) and " cmd" not in line and "what" not in line, line


def test_simulate_help_names_the_scene_keys_and_describes_every_option(capsys):
    from cstomo_sensor.model.simulate import MISMATCH_KEYS, SCENE_KEYS
    from cstomo_sensor.tools.cli import build_parser

    with pytest.raises(SystemExit) as done:
        cstomo(["simulate", "--help"])
    assert done.value.code == 0
    text = capsys.readouterr().out
    missing = [k for k in SCENE_KEYS + MISMATCH_KEYS + ("socket", "patches", "inclusion", "total_force")
               if k not in text]
    assert not missing, text
    sim = build_parser()._subparsers._group_actions[0].choices["simulate"]
    assert all(a.help for a in sim._actions), [a.dest for a in sim._actions if not a.help]


@pytest.mark.parametrize("text,key", [("snr: 40\n", "'snr'"), ("mismatch: {jitter: 0.001}\n", "'mismatch.jitter'")])
def test_a_scene_file_with_an_unknown_key_is_refused_naming_it(tmp_path, text, key):
    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.model.simulate import Scene

    f = tmp_path / "scene.yaml"
    f.write_text("loads:\n  - {socket: {force: [0, 0, -10]}}\n" + text)
    with pytest.raises(ConfigError, match=key):
        Scene.load(f)


@pytest.mark.parametrize("text,why", [
    ("snr_db: sixty\n", "snr_db='sixty': expected a number (dB) or null"),
    ("seed: -3\n", "seed=-3: expected an integer >= 0"),
    ("seed: abc\n", "seed='abc': expected an integer >= 0"),
    ("frames_per_load: 0\n", "frames_per_load=0: expected an integer >= 1"),
    ("truth_mesh_size: 3\n", "truth_mesh_size=3: expected 0.0002..0.02 m"),
    ("mismatch: {contact_impedance: -0.5}\n", "mismatch.contact_impedance=-0.5: expected a fraction 0..1"),
])
def test_a_scene_file_with_a_bad_value_is_refused_naming_it(tmp_path, text, why):
    """Before: a TypeError or ValueError traceback (snr_db: sixty only once the truth's mesh was built)."""
    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.model.simulate import Scene

    f = tmp_path / "scene.yaml"
    f.write_text("loads:\n  - {socket: {force: [0, 0, -10]}}\n" + text)
    with pytest.raises(ConfigError) as err:
        Scene.load(f)
    assert str(err.value) == f"{f}: {why}"
    f.write_text("loads:\n  - {socket: {force: [0, 0, -10]}}\ntruth_mesh_size: 3e-3\nsnr_db: 40\n")
    scene = Scene.load(f)  # YAML reads 3e-3 (no dot) as a string: still a number here
    assert scene.truth_mesh_size == pytest.approx(0.003) and scene.snr_db == 40


def test_a_timeline_load_with_a_time_that_is_no_number_is_refused_naming_it(tmp_path):
    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.model.timeline import Timeline

    f = tmp_path / "scene.yaml"
    f.write_text("timeline:\n  duration: 5\n  loads:\n    - {time: soon, force: [0, 0, -20]}\n")
    with pytest.raises(ConfigError, match=re.escape("timeline.loads[0].time='soon': expected seconds, a number")):
        Timeline.from_scene(f)


def run_cstomo(argv: list[str], capsys=None) -> tuple[int, str, str]:
    """``cstomo ARGV``: (exit status, stdout, stderr); as its own process without ``capsys``, else its
    main() in this process (no ~2-3 s start of a process: the refusals before any computation)."""
    if capsys is None:
        r = subprocess.run([str(Path(sys.executable).parent / "cstomo"), *argv], capture_output=True, text=True,
                           timeout=120, env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
        return r.returncode, r.stdout, r.stderr
    capsys.readouterr()
    try:
        code = cstomo(argv)
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    out, err = capsys.readouterr()
    return code, out, err


@pytest.mark.parametrize("load,why,process", [
    pytest.param("{socket: {force: [0, -10]}}", "socket force \\[0, -10\\] has 2 components, not 3", True,
                 marks=pytest.mark.slow, id="process"),  # starts a process
    pytest.param("{socket: {magnitude: 20}}", "missing 'elevation_deg'", False, id="in-process-1"),
    pytest.param("{inclusion: {center: [0, 0, 0.01]}}", "missing 'radius'", False, id="in-process-2")])
def test_cstomo_simulate_refuses_a_malformed_load_in_one_line(tmp_path, capsys, load, why, process):
    """Before: an IndexError traceback out of write_forces (a 2-component force, after frames.csv and
    reference.csv were written) or a KeyError traceback (a missing key). The first case is the
    ``cstomo`` process itself (its exit status, its one line, no traceback; slow: it starts a process),
    the others its main() in this process (a traceback there fails the test as well)."""
    f = tmp_path / "scene.yaml"
    f.write_text(f"loads:\n  - {{socket: {{force: [0, 0, -10]}}}}\n  - {load}\n")
    out = tmp_path / "out"
    code, _, err = run_cstomo(["simulate", "--scene", str(f), "--out", str(out)], None if process else capsys)
    assert code == 2 and "Traceback" not in err, err
    (line,) = err.strip().splitlines()
    assert re.match(f"^cstomo simulate: error: {re.escape(str(f))}: loads\\[1\\]: load .*: {why}; expected socket: ", line), line
    assert "(docs/formats.md#scene-file)" in line and not out.exists()


SCENES = Path(__file__).resolve().parent.parent / "scenes"


@pytest.mark.parametrize("text,why", [
    ("loads:\n  - {socket: {force: [0, 0, -20]}}\n  - {socket: {force: [0, 1200, -1600]}}\n",
     "loads[1] (socket) is 2000 N"),
    ("loads:\n  - {socket: {magnitude: 60.5, elevation_deg: 90}}\n", "loads[0] (socket) is 60.5 N"),
    ("timeline:\n  duration: 5\n  loads:\n    - {time: 1, force: [0, 0, -20]}\n"
     "    - {time: 2, magnitude: 75, elevation_deg: 90}\n", "timeline.loads[1] (time 2 s) is 75 N"),
    ("timeline: {duration: 50, tasks: {magnitude: [5, 80]}}\n", "tasks.magnitude=[5.0, 80.0]"),
])
def test_simulate_and_board_sim_refuse_a_scene_socket_load_beyond_the_range_before_computing(tmp_path, capsys, text, why):
    """A scene's socket load beyond 60 N (1.5 x the rated 40 N, the limit of a load script) is refused in
    one line naming the file, the load, its magnitude and the range: no 'computing' line, nothing written.
    The commands' main() in this process (the refusal comes before any computation; the ``cstomo`` process
    itself: test_cstomo_simulate_refuses_a_malformed_load_in_one_line)."""
    f = tmp_path / "scene.yaml"
    f.write_text(text)
    for cmd, args, prefix in (("simulate", ["--out", str(tmp_path / "out")], "cstomo simulate: error: "),
                              ("board-sim", ["--link", str(tmp_path / "b")], "cstomo board-sim: error: ")):
        code, out, err = run_cstomo([cmd, "--scene", str(f), *args], capsys)
        assert code == 2 and out == "", out + err
        (line,) = err.strip().splitlines()
        assert line.startswith(f"{prefix}{f}: {why}") and "0..60 N" in line, line
    assert not (tmp_path / "out").exists() and not (tmp_path / "b").exists()


def test_every_shipped_scene_loads_and_a_60_n_socket_load_is_accepted(tmp_path):
    from cstomo_sensor.model.simulate import Scene
    from cstomo_sensor.model.timeline import Timeline

    scenes = sorted(SCENES.glob("*.yaml"))  # scenes/devices/ holds sensor files, not scenes
    assert len(scenes) >= 13
    for scene in scenes:
        loaded = Scene.load(scene)
        if loaded.timeline is not None:
            Timeline.from_scene(scene)  # parses the timeline (its loads, tasks, load script); builds no mesh
    f = tmp_path / "scene.yaml"
    f.write_text("loads:\n  - {socket: {force: [0, 36, -48]}}\n")  # 60 N: the limit is inclusive
    assert np.linalg.norm(Scene.load(f).loads[0].force) == pytest.approx(60.0, abs=1e-9)


def test_the_demo_prints_no_angles_for_no_force():
    """Columns |F| N, elevation and azimuth in degrees (their units in the header): no angles for no
    force; a force straight down has an elevation (90) and no azimuth (before: 'az 0.0' for the true
    force, 'az -52.9' for its estimate)."""
    from cstomo_sensor.tools.demo import FORCE_COLUMNS, _fmt

    assert FORCE_COLUMNS.split() == ["|F|", "[N]", "elev", "[deg]", "azim", "[deg]"]
    assert _fmt(np.zeros(3)).split() == ["0.00", "-", "-"]
    assert len(_fmt(np.zeros(3))) == len(_fmt(np.array([0.0, 0.0, -20.0]))) == len(FORCE_COLUMNS)  # aligned
    assert _fmt(np.array([0.0, 0.0, -20.0])).split() == ["20.00", "90.0", "-"]
    # the estimate of a vertical load: 0.4 deg off vertical is a horizontal part of 0.14 N, below 2 x 0.3 N
    tilted = 20.0 * np.array([np.sin(np.radians(0.4)) * np.cos(np.radians(-52.9)),
                              np.sin(np.radians(0.4)) * np.sin(np.radians(-52.9)), -np.cos(np.radians(0.4))])
    assert _fmt(tilted, sigma_n=0.3).split() == ["20.00", "89.6", "-"]


def test_the_demo_shows_azimuths_0_to_360_as_its_labels_say():
    """'sweep azimuth 225°' shows 225.0 (before: -135.0 beside the label 225); the paper's 120° in the
    x-z plane is elevation 60 at azimuth 180, as its label and the legend say."""
    from cstomo_sensor.angles import force_from_angles
    from cstomo_sensor.tools.demo import LEGEND, _fmt, load_script

    times, forces, labels = load_script()
    sweep = forces[labels.index("sweep azimuth 225°")]
    assert _fmt(sweep).split() == ["20.00", "60.0", "225.0"]
    assert _fmt(forces[labels.index("paper 120° in x-z")]).split() == ["20.00", "60.0", "180.0"]
    assert "x-z" in LEGEND and "0..360" in LEGEND
    assert _fmt(force_from_angles(20.0, np.radians(60.0), np.radians(-0.01))).split()[-1] == "0.0"  # not 360.0


def test_the_demo_prints_no_angles_for_a_force_within_twice_its_sigma():
    """Before: an unloaded line read '0.02 N  el  -15.8  az   -76.3', a direction of noise. Its sigma_n
    (the node's ~/wrench_sigma) is about 0.3 N on the demo's 60 dB board: below 2 sigma_n, no angles."""
    from cstomo_sensor.angles import force_from_angles
    from cstomo_sensor.tools.demo import _fmt, judge

    noise = force_from_angles(0.02, np.radians(-15.8), np.radians(-76.3))
    assert _fmt(noise, sigma_n=0.3).split() == ["0.02", "-", "-"]
    assert _fmt(noise).split() == ["0.02", "-15.8", "283.7"]  # sigma unknown: shown (azimuth 0..360)
    small = force_from_angles(0.61, 0.0, np.radians(45.0))  # just above 2 x 0.3 N, horizontal: shown
    assert _fmt(small, sigma_n=0.3).split() == ["0.61", "0.0", "45.0"]
    steep = force_from_angles(0.61, np.radians(30.0), np.radians(45.0))  # its horizontal part 0.53 N: no azimuth
    assert _fmt(steep, sigma_n=0.3).split() == ["0.61", "30.0", "-"]
    assert _fmt(force_from_angles(0.59, np.radians(60.0), 0.0), sigma_n=0.3).split()[1:] == ["-", "-"]
    assert len({len(_fmt(f, sigma_n=0.3)) for f in (noise, small, np.zeros(3), np.array([0.0, 0.0, -20.0]))}) == 1
    # a demo line of the unloaded sensor: the estimate's columns say no direction, aligned with a loaded line
    times, forces = np.array([0.0, 3.0]), np.array([[0.0, 0.0, 0.0], [0.0, 0.0, -20.0]])
    unloaded, counted = judge(times, forces, ["unloaded (tare)", "down"], 1.0, noise, 0.3)
    loaded, _ = judge(times, forces, ["unloaded (tare)", "down"], 4.0, np.array([0.3, 0.0, -20.1]), 0.3)
    assert counted is None and unloaded.split()[-4:] == ["0.02", "-", "-", "-"], unloaded
    assert len(unloaded) == len(loaded) and loaded.split()[-4:-1] == ["20.10", "89.1", "-"], loaded


@pytest.mark.slow
def test_board_sim_says_it_computes_only_when_it_does(tmp_path):
    """board-sim's '20-60 s' line is printed on a cold cache (it computes the frames), not on the next
    run of the same inputs (it reads them from the cache in a fraction of a second). In the suite's cache
    (the simulator's mesh and model shared with the other tests), a scene of an inclusion no run has
    asked for: its frames are the one miss, a second's work (an empty cache of its own built the mesh
    once more, and a socket load's mechanics takes 15-40 s in every process that computes one)."""
    import uuid

    radius = 0.003 + uuid.uuid4().int % 10**6 * 1e-10  # this run's own (1e-10 m steps: never another run's)
    scene = tmp_path / "scene.yaml"
    scene.write_text(f"loads:\n  - {{inclusion: {{center: [0, 0, 0.01], radius: {radius:.10f}, contrast: 2}}}}\n")
    exe = Path(sys.executable).parent / "cstomo"
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    said = []
    for _ in range(2):
        p = subprocess.Popen([str(exe), "board-sim", "--scene", str(scene), "--rate", "10"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        try:
            assert p.stdout.readline().startswith("device: ")  # the frames are ready
            p.send_signal(2)
            _, err = p.communicate(timeout=30)
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
        assert p.returncode == 0, err
        said.append("20-60 s" in err)
    assert said == [True, False], said


def test_a_command_prints_one_log_message_at_most_three_times(capsys):
    """Before: `cstomo bench --drift` printed about 800 lines of 'implausible frames ...' and 'plausible
    frames again ...' (one pair per stream it ran). A command's log lets a message template through 3
    times, then counts it and says so once at the end."""
    import logging

    from cstomo_sensor.tools.common import MAX_REPEATS, setup_logging

    repeats = setup_logging(force=True)
    log = logging.getLogger("cstomo_sensor.frame_path.health")
    for i in range(400):
        log.warning("implausible frames (no force output): %s", f"reason {i}")
        log.warning("plausible frames again after %d implausible ones", i)
    logging.getLogger("cstomo_sensor.other").warning("something else")
    for _ in range(20):  # not shown (INFO), so neither counted nor summarised (before: scikit-fem's INFO lines)
        logging.getLogger("skfem.assembly").info("Assembling finished.")
    err = capsys.readouterr().err.splitlines()
    assert MAX_REPEATS == 3
    assert sum("implausible frames" in ln for ln in err) == 3 and sum("plausible frames again" in ln for ln in err) == 3
    assert any("something else" in ln for ln in err)
    summary = repeats.summary()
    assert len(summary) == 2 and "came 400 times; the 397 after the first 3 not shown" in summary[0], summary
    import atexit

    atexit.unregister(repeats.say)
    for h in [h for h in logging.getLogger().handlers if getattr(h, "_cstomo", False)]:
        logging.getLogger().removeHandler(h)


def test_the_robot_bench_says_a_window_without_forces_in_words():
    """Before: 'err nan N, angle nan deg' for a window whose every frame was refused, and 'sigma_n
    45.306 N (50.66 x the error)' without saying whether that is good."""
    from cstomo_sensor.tools.bench.robot import describe

    assert describe({"err_n": math.nan, "implausible": 300, "frames": 300}) == \
        "no force published (300 of 300 frames implausible)"
    row = {"err_n": 0.894, "implausible": 0, "frames": 300, "angle_deg": 1.2, "magnitude_pct": 3.1, "wrong_pct": 2.0,
           "sigma_n": 45.306, "sigma_ratio": 50.66, "over3sigma_pct": 0.0}
    text = describe(row)
    assert "nan" not in text and "50.7 x the median error (over-cautious" in text, text
    assert "(covers the error)" in describe({**row, "sigma_n": 1.2, "sigma_ratio": 1.34})
    assert "(smaller than the error)" in describe({**row, "sigma_n": 0.4, "sigma_ratio": 0.45})


def test_progress_is_one_updating_line_on_a_terminal_and_nothing_elsewhere(monkeypatch, tmp_path):
    """A long step of the core (a timeline's knots, a simulation's loads) logs its progress
    (cstomo_sensor.progress.steps); a command shows it as one line updated in place on a terminal
    (a real pseudo-terminal here) and leaves it out of a file, while its warnings reach both."""
    import logging
    import time as _time

    from cstomo_sensor import progress
    from cstomo_sensor.tools.common import setup_logging

    log = logging.getLogger("cstomo_sensor.model.timeline")
    clock = iter(np.arange(0.0, 100.0, 0.6))  # each item takes 0.6 s: a record every other item
    # the progress module's own clock only (patching time.monotonic itself reaches every thread of the process:
    # a thread left by an earlier test spun on it once, and CI hung here)
    from types import SimpleNamespace
    monkeypatch.setattr(progress, "time", SimpleNamespace(monotonic=lambda: next(clock)))

    def run_on(stream):
        monkeypatch.setattr(sys, "stderr", stream)
        repeats = setup_logging(force=True)
        try:
            assert list(progress.steps(range(10), log, "timeline: the truth at its knots")) == list(range(10))
            log.warning("a warning after it")
        finally:
            import atexit

            atexit.unregister(repeats.say)
            for h in [h for h in logging.getLogger().handlers if getattr(h, "_cstomo", False)]:
                logging.getLogger().removeHandler(h)
        stream.flush()

    master, slave = os.openpty()
    with open(slave, "w", closefd=True) as tty:
        assert tty.isatty()
        run_on(tty)
        _time.sleep(0.1)
        import select
        assert select.select([master], [], [], 5.0)[0], "nothing written on the terminal"
        text = os.read(master, 65536).decode()
    os.close(master)
    assert text.count("\rtimeline") == 6 and "timeline: the truth at its knots: 0/10" in text, repr(text)
    assert "timeline: the truth at its knots: 10/10" in text, repr(text)
    assert "\n" not in text.split("10/10")[0], repr(text)  # one line, updated in place, until the last item
    assert text.rstrip().splitlines()[-1].endswith("a warning after it"), repr(text)
    with open(tmp_path / "log.txt", "w") as f:  # a file (CI, a pipe): no progress, the warning stays
        run_on(f)
    assert (tmp_path / "log.txt").read_text().splitlines() == ["WARNING cstomo_sensor.model.timeline: a warning after it"]


def test_every_flag_of_every_command_has_help_and_shows_its_default():
    """--help: every option with a help text, its default shown (by the shared formatter, so a flag
    added later shows it too), no internal file paths (force/slow_states/drift.py), --cache-dir naming
    $XDG_CACHE_HOME as the cache does; calibrate's help was 99 lines, replay's 86."""
    import argparse
    import re

    from cstomo_sensor.tools.cli import OWN_PARSERS, build_parser, subcommand_parser
    from cstomo_sensor.tools.common import HelpFormatter

    commands = [[], ["model", "build"], ["model", "voltages"], ["reconstruct"], ["estimate"], ["simulate"],
                *[[k] for k in OWN_PARSERS]]
    for words in commands:
        p = subcommand_parser(words)[0] if words else build_parser()
        text = p.format_help()
        assert p.formatter_class is HelpFormatter, words
        assert not re.search(r"\b\w+/\w+\.py\b", text), (words, re.search(r"\b\w+/\w+\.py\b", text))
        assert len(text.splitlines()) <= 80, (words, len(text.splitlines()))
        fmt = p._get_formatter()
        for a in p._actions:
            if not a.option_strings or isinstance(a, argparse._HelpAction):
                continue
            assert a.help, (words, a.option_strings)
            shown = a.default is not None and a.default is not False and a.nargs != 0
            if shown or isinstance(a, argparse.BooleanOptionalAction):
                assert "default" in fmt._get_help_string(a).lower(), (words, a.option_strings, a.help)
        if any("--cache-dir" in a.option_strings for a in p._actions):
            assert "XDG_CACHE_HOME" in text, words
    # a flag added without a default in its help gets it from the formatter
    p = subcommand_parser(["demo"])[0]
    p.add_argument("--reference-age", type=float, default=3600.0, help="seconds")
    assert "--reference-age REFERENCE_AGE" in p.format_help() and "(default: 3600.0)" in p.format_help()


@pytest.mark.parametrize("words, flag, value, expected", [
    (["demo"], "--hold", "0", "seconds > 0"), (["demo"], "--rate", "-5", "frames per second > 0"),
    (["board-sim", "--load-script", "x.csv"], "--duration", "0", "seconds > 0"),
    (["estimate", "--reference", "r", "--frames", "f", "--out", "o"], "--rate", "0", "frames per second > 0"),
    (["calibrate", "--out", "d.yaml"], "--stamp-tolerance", "0", "seconds > 0"),
    (["calibrate", "--out", "d.yaml"], "--creep-rate", "nan", "frames per second > 0"),
    (["bench", "--out", "o"], "--heldout", "0", "a whole number >= 1"),
    (["bench-node"], "--seconds", "-1", "seconds > 0"), (["bench-node"], "--rates", "inf", "frames per second > 0")])
def test_a_bad_number_is_refused_at_parsing_in_one_line(capsys, words, flag, value, expected):
    """Before: `cstomo demo --hold 0` exited 0 showing no load, `--hold -3` failed after the model
    loaded naming a temporary file the user never wrote."""
    from cstomo_sensor.tools.cli import subcommand_parser

    parser, rest = subcommand_parser(words)
    with pytest.raises(SystemExit) as exc:
        parser.parse_args([*rest, flag, value])
    assert exc.value.code == 2
    assert capsys.readouterr().err.splitlines() == [f"{parser.prog}: error: argument {flag}: {value}: expected {expected}"]
