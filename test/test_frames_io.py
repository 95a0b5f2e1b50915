"""The CSV readers of docs/formats.md and the command line on bad input files: every
problem is a package error naming the file and the line, never a raw ValueError or a lost row; the
tools print one line, exit 2 and leave no half-written output."""
from __future__ import annotations

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from cstomo_sensor.errors import ConfigError, CstomoError, FrameError
from cstomo_sensor.frames_io import (
    read_forces,
    read_frames,
    read_load_script,
    write_forces,
    write_frames,
)

ROW = ",".join(["1.0"] * 208)


def _write(tmp_path: Path, data: bytes | str, name: str = "f.csv") -> Path:
    p = tmp_path / name
    p.write_bytes(data.encode() if isinstance(data, str) else data)
    return p


# --- frames ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("data, where", [
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", ":1:"),                 # binary
    (f"# ok\n{ROW}\n".encode() + b"1.0,\xff\xfe,2\n", ":3:"),        # not UTF-8 on line 3
    (f"{ROW}\n{ROW},1.0\n", ":2:"),                                  # ragged: 209 values
    (f"{ROW}\n" + ",".join(["1.0"] * 207) + ",x\n", ":2:"),          # a bad cell
    (f"{ROW}\n" + ",".join(["1.0"] * 207) + ",\n", ":2:"),           # an empty cell
    (f"{ROW}\n" + ",".join(["1.0"] * 207) + ",nan\n", ":2:"),        # NaN
])
def test_read_frames_names_file_and_line(tmp_path, data, where):
    p = _write(tmp_path, data)
    with pytest.raises(FrameError, match=f"{p}{where}"):
        read_frames(p)


def test_frames_round_trip(tmp_path):
    f = np.random.default_rng(0).normal(size=(3, 208))
    write_frames(tmp_path / "f.csv", f, comment="a\nb")
    np.testing.assert_allclose(read_frames(tmp_path / "f.csv"), f, rtol=1e-8)


# --- forces ---------------------------------------------------------------------------------------

def test_forces_round_trip_and_optional_columns(tmp_path):
    f = np.array([[1.0, 2.0, -3.0], [0.0, 0.5, -20.0]])
    write_forces(tmp_path / "f.csv", f)
    np.testing.assert_allclose(read_forces(tmp_path / "f.csv"), f, rtol=1e-8)
    p = _write(tmp_path, "frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg,valid,consistency,foreign_load,extra\n"
                         "0,1,2,-3,3.7,0.9,1.1,1,0.5,0,x\n"
                         "1,,,,,,,0,,,\n")
    got = read_forces(p)
    np.testing.assert_allclose(got[0], [1, 2, -3])
    assert np.isnan(got[1]).all()  # a rejected frame: no force


@pytest.mark.parametrize("data, where", [
    ("frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg\n0,1,2,3,4,5,6\n1,1,2,3\n", ":3:"),       # ragged
    ("frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg\n0,1,zz,3,4,5,6\n", ":2:"),               # bad cell
    ("frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg\n0,1,,3,4,5,6\n", ":2:"),                 # empty, no valid=0
    ("frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg\n0,1,inf,3,4,5,6\n", ":2:"),              # non-finite
    ("0,1,2,3,4,5,6\n1,1,2,3,4,5,6\n", ":1:"),                                             # no header
    (b"frame,fx,fy,fz\n0,1,2,\xff\n", ":2:"),                                              # not UTF-8
])
def test_read_forces_names_file_and_line(tmp_path, data, where):
    p = _write(tmp_path, data)
    with pytest.raises(FrameError, match=f"{p}{where}"):
        read_forces(p)


# --- load scripts ---------------------------------------------------------------------------------

def test_load_script_round_trip(tmp_path):
    p = _write(tmp_path, "time,fx,fy,fz\n0,0,0,0\n# a comment\n1.5,0,0,-20\n")
    t, f = read_load_script(p)
    np.testing.assert_array_equal(t, [0.0, 1.5])
    np.testing.assert_array_equal(f, [[0, 0, 0], [0, 0, -20]])


@pytest.mark.parametrize("data, where, what", [
    ("0,0,0,0\n1.5,0,0,-20\n", ":1:", "header"),                         # no header: its first row was lost
    ("time,fx,fy,fz\n0,0,0,0\nnan,0,0,-20\n", ":3:", "time"),            # NaN time
    ("time,fx,fy,fz\n0,0,0,0\n1,0,0\n", ":3:", "4"),                     # ragged
    ("time,fx,fy,fz\n0,0,0,0\n1,0,0,lots\n", ":3:", "fz"),               # bad cell
    ("time,fx,fy,fz\n2,0,0,0\n1,0,0,-20\n", ":3:", "decrease"),          # times go back
    ("time,fx,fy,fz\n", "", "no rows"),                                  # header only
    (b"time,fx,fy,fz\n\x00\x01\x02\n", ":2:", "UTF-8|binary"),           # binary
])
def test_read_load_script_names_file_and_line(tmp_path, data, where, what):
    p = _write(tmp_path, data)
    with pytest.raises(ConfigError, match=f"{p}{where}.*({what})"):
        read_load_script(p)


# --- fuzz: only package errors come out ------------------------------------------------------------

_csv_text = st.lists(st.lists(st.one_of(st.sampled_from(["0", "1.5", "-2e-3", "", "nan", "inf", "x", " 3 ", "1e999"]),
                                        st.text(max_size=4)), max_size=10), max_size=6) \
    .map(lambda rows: "\n".join(",".join(r) for r in rows))
_bytes = st.one_of(st.binary(max_size=300), _csv_text.map(lambda t: t.encode("utf-8", "surrogatepass")),
                   st.builds(lambda h, t: (h + "\n" + t).encode("utf-8", "surrogatepass"),
                             st.sampled_from(["time,fx,fy,fz", "frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg",
                                              "frame,fx,fy,fz,valid", ROW]), _csv_text))


@pytest.mark.slow  # seconds of computation
@settings(max_examples=300, deadline=None)
@given(raw=_bytes)
def test_fuzz_readers_raise_only_package_errors(tmp_path_factory, raw):
    p = tmp_path_factory.getbasetemp() / "fuzz.csv"
    p.write_bytes(raw)
    for reader in (read_frames, read_forces, read_load_script):
        try:
            out = reader(p)
        except CstomoError:
            continue
        for a in (out if isinstance(out, tuple) else (out,)):
            assert isinstance(a, np.ndarray) and a.dtype == float


# --- the command line on bad input ------------------------------------------------------------------

def _cstomo(capfd, *args: str, process: bool = False) -> subprocess.CompletedProcess:
    """``cstomo ARGS``: its main() in this process (every refusal here comes before any computation, no
    ~2-3 s start of a process each), or with ``process`` the ``cstomo`` process itself (its exit status,
    its one line, no traceback: one case below). A command's signal handlers are put back after it."""
    if process:
        return subprocess.run([str(Path(sys.executable).parent / "cstomo"), *args], capture_output=True, text=True,
                              timeout=120, env=dict(os.environ, OPENBLAS_NUM_THREADS="1"))
    import signal

    from cstomo_sensor.tools.cli import main

    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    capfd.readouterr()
    try:
        code = main(list(args))
    except SystemExit as exc:  # argparse's own refusals
        code = exc.code
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    out, err = capfd.readouterr()
    return subprocess.CompletedProcess(list(args), code, out, err)


@pytest.mark.parametrize("cmd,process", [pytest.param("estimate", True, marks=pytest.mark.slow),  # starts cstomo
                                         ("reconstruct", False)])
def test_cli_bad_frames_file_one_line_exit_2_no_output(tmp_path, capfd, cmd, process):
    good = _write(tmp_path, f"{ROW}\n", "ref.csv")
    bad = _write(tmp_path, f"{ROW}\n{ROW},1\n", "frames.csv")  # ragged line 2
    out = tmp_path / ("out.csv" if cmd == "estimate" else "out.npz")
    r = _cstomo(capfd, cmd, "--reference", str(good), "--frames", str(bad), "--out", str(out), "--cache-dir",
                str(tmp_path / "cache"), process=process)
    assert r.returncode == 2, r.stdout + r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert f"{bad}:2:" in r.stderr
    assert not out.exists() and not list(tmp_path.glob("out*"))
    assert not (tmp_path / "cache").exists()  # the input was read before any model was built


@pytest.mark.parametrize("cmd", ["estimate", "reconstruct"])
def test_cli_out_in_a_missing_directory_is_refused_first_in_one_line(tmp_path, capfd, cmd):
    """Before: the model was built and the command then failed with '[Errno 2] No such file or
    directory: '.../missing/.out.csv.tmp1234'', naming a temporary file the user never gave."""
    good = _write(tmp_path, f"{ROW}\n", "ref.csv")
    out = tmp_path / "missing" / "out.csv"
    r = _cstomo(capfd, cmd, "--reference", str(good), "--frames", str(good), "--out", str(out), "--cache-dir",
                str(tmp_path / "cache"))
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stdout + r.stderr
    assert r.stderr.strip().splitlines() == [f"cstomo {cmd}: error: --out {out}: no directory {out.parent}; "
                                             "expected a file in an existing directory"], r.stderr
    assert not (tmp_path / "cache").exists()  # refused before any model was built
    from cstomo_sensor.frames_io import atomic_write

    with pytest.raises(OSError, match=f"^{out}: cannot be written \\(No such file or directory\\)$"):
        with atomic_write(out) as f:
            f.write(b"x")


def test_cli_board_sim_and_demo_refuse_a_load_script_without_header(tmp_path, capfd):
    script = _write(tmp_path, "0,0,0,0\n1.5,0,0,-20\n", "load.csv")
    for args in (["board-sim", "--sensor", "cuboid_joint", "--load-script", str(script), "--rate", "10"],
                 ["demo", "--load-script", str(script)]):
        r = _cstomo(capfd, *args)
        assert r.returncode == 2, r.stdout + r.stderr
        assert "Traceback" not in r.stderr and f"{script}:1:" in r.stderr and "header" in r.stderr, r.stderr
        assert len(r.stderr.strip().splitlines()) == 1, r.stderr  # refused before board-sim's 'computing' line
    good = _write(tmp_path, "time,fx,fy,fz\n0,0,0,0\n", "good.csv")
    r = _cstomo(capfd, "board-sim", "--load-script", str(good), "--rate", "-5")  # before: refused after computing
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [
        "cstomo board-sim: error: argument --rate: -5: expected frames per second > 0"], r.stderr
    for flag, value, what in (("--hold", "0", "seconds > 0"), ("--hold", "-3", "seconds > 0"),
                              ("--rate", "0", "frames per second > 0"), ("--rate", "-5", "frames per second > 0")):
        r = _cstomo(capfd, "demo", flag, value)  # before: --hold 0 exited 0 showing no load, the others failed late
        assert r.returncode == 2 and r.stderr.strip().splitlines() == [  # on a temporary file the user never wrote
            f"cstomo demo: error: argument {flag}: {value}: expected {what}"], r.stderr


def test_cli_board_sim_and_demo_refuse_a_load_beyond_the_range_before_computing(tmp_path, capfd):
    """2000 N is 50 x the rated 40 N (docs/physics.md): one line naming the load, its time and the
    accepted range, before board-sim's 'computing' line (nothing simulated)."""
    script = _write(tmp_path, "time,fx,fy,fz\n0,0,0,0\n3,0,0,-20\n6,0,1200,-1600\n", "load.csv")
    for cmd in ("board-sim", "demo"):
        r = _cstomo(capfd, cmd, "--load-script", str(script), *(["--link", str(tmp_path / "b")] if cmd == "board-sim" else []))
        assert r.returncode == 2 and r.stdout == "", r.stdout + r.stderr
        assert r.stderr.strip().splitlines() == [
            f"cstomo {cmd}: error: {script}:4: load 3 (time 6 s) is 2000 N; expected a magnitude of 0..60 N"], r.stderr
    assert not (tmp_path / "b").exists()


def test_load_script_magnitude_limit_is_inclusive(tmp_path):
    from cstomo_sensor.errors import ConfigError

    p = _write(tmp_path, "time,fx,fy,fz\n0,36,0,-48\n1,0,0,-60.001\n", "load.csv")
    with pytest.raises(ConfigError, match=r":3: load 2 \(time 1 s\) is 60.001 N; expected a magnitude of 0..60 N$"):
        read_load_script(p, max_force=60.0)
    t, f = read_load_script(p)  # no limit asked: as before
    assert np.allclose(np.linalg.norm(f, axis=1), [60.0, 60.001], rtol=0, atol=1e-9)


def test_atomic_write_leaves_no_half_written_file(tmp_path):
    from cstomo_sensor.frames_io import atomic_write

    target = tmp_path / "out.csv"
    target.write_text("old\n")
    with pytest.raises(RuntimeError):
        with atomic_write(target) as f:
            f.write(b"half")
            raise RuntimeError("disk full")
    assert target.read_text() == "old\n" and os.listdir(tmp_path) == ["out.csv"]
    with atomic_write(target) as f:
        f.write(b"new\n")
    assert target.read_text() == "new\n" and os.listdir(tmp_path) == ["out.csv"]


def test_forces_file_consistency_columns(tmp_path):
    """The optional consistency and foreign_load columns (docs/formats.md#forces-file): written after
    valid, empty for a frame without a statistic, ignored by the reader."""
    from cstomo_sensor.errors import FrameError
    from cstomo_sensor.frames_io import read_forces, write_forces

    f = np.array([[1.0, 2.0, -3.0], [np.nan] * 3, [0.0, 0.0, -5.0]])
    write_forces(tmp_path / "f.csv", f, valid=np.array([True, False, True]),
                 consistency=np.array([1.25, np.nan, 40.0]), foreign_load=np.array([False, False, True]))
    lines = (tmp_path / "f.csv").read_text().splitlines()
    assert lines[0] == "frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg,valid,consistency,foreign_load"
    assert lines[1].endswith(",1,1.25,0") and lines[2] == "1,,,,,,,0,," and lines[3].endswith(",1,40,1")
    back, valid = read_forces(tmp_path / "f.csv", with_valid=True)
    assert valid.tolist() == [True, False, True] and np.array_equal(back[[0, 2]], f[[0, 2]])
    with pytest.raises(FrameError, match="both or neither"):
        write_forces(tmp_path / "g.csv", f, consistency=np.zeros(3))


def test_the_forces_file_gives_its_angles_in_degrees_and_says_so(tmp_path):
    """A person reads the forces file: its header names the unit (elevation_deg, azimuth_deg), the
    azimuth is 0..360 (a force towards -x-y at 60 deg below the horizontal reads 225, not -135), and a
    vertical force has azimuth 0. Expected values by hand: (-cos60 cos45, -cos60 sin45, -sin60) x 20 N."""
    f = 20.0 * np.array([[-0.5 * np.sqrt(0.5), -0.5 * np.sqrt(0.5), -np.sqrt(3) / 2], [0.0, 0.0, -20.0 / 20.0],
                         [10.0 / 20.0, 0.0, 0.0]])
    path = tmp_path / "f.csv"
    write_forces(path, f)
    rows = list(csv.DictReader(path.read_text().splitlines()))
    assert list(rows[0]) == ["frame", "fx", "fy", "fz", "magnitude", "elevation_deg", "azimuth_deg"]
    got = [(float(r["magnitude"]), float(r["elevation_deg"]), float(r["azimuth_deg"])) for r in rows]
    assert np.allclose(got, [(20.0, 60.0, 225.0), (20.0, 90.0, 0.0), (10.0, 0.0, 0.0)], atol=1e-6), got
