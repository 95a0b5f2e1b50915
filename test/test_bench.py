"""`cstomo bench --smoke` and `cstomo render`: outputs exist and parse, and the table's accuracy
columns are the numbers `cstomo estimate` gives on the same frames. No timing assertions."""
import csv

import numpy as np
import pytest

pytestmark = pytest.mark.slow  # the benchmark's smoke run (~33 s) and rendering


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    from cstomo_sensor.tools.bench import table

    out = tmp_path_factory.mktemp("bench")
    return out, table.run("smoke", out, say=lambda msg: None)


def _rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_smoke_outputs_parse(smoke):
    from cstomo_sensor.tools.bench import table

    out, res = smoke
    rows = _rows(out / "table.csv")
    assert rows and set(table.TABLE_COLS) <= set(rows[0])
    d = next(r for r in rows if r["setting"] == "default")
    for k in table.TABLE_COLS[table.TABLE_COLS.index("weight_power"):]:  # the numeric columns
        assert np.isfinite(float(d[k])), k
    stab = _rows(out / "stability.csv")
    assert set(table.STAB_COLS) <= set(stab[0])
    cases = {r["case"] for r in stab}
    assert any(c.startswith("force_N") for c in cases) and "snr_db" in cases
    assert any(c.startswith("dead electrode") for c in cases)
    assert all(r["finite"] == "True" for r in stab)
    # exactly zero force, frame equal to the reference: the estimate is ~0 (no bias)
    zero = next(r for r in stab if r["case"].startswith("force_N noise-free"))
    assert float(zero["max_force_n"]) < 0.5
    png = out / "tradeoff.png"
    assert png.is_file() and png.stat().st_size > 1000
    assert "| default |" in (out / "table.md").read_text()


def test_default_row_matches_cstomo_estimate(smoke, tmp_path, capsys):
    from cstomo_sensor.frames_io import read_forces, read_frames, write_frames
    from cstomo_sensor.tools.bench import scenes
    from cstomo_sensor.tools.cli import main

    out, res = smoke
    # the frames the bench used are exactly what its frames file holds, and re-written the same
    frames = read_frames(out / "frames.csv")
    write_frames(tmp_path / "frames.csv", frames)
    assert np.array_equal(read_frames(tmp_path / "frames.csv"), frames)
    # the table's frames are independent loads, not a time series: estimated frame by frame, without
    # the stream's drift tracking (cstomo bench --drift measures it); creep compensation, which acts on
    # a history in time, turns itself off on such a file and says so
    assert main(["estimate", "--reference", str(out / "reference.csv"), "--frames", str(tmp_path / "frames.csv"),
                 "--out", str(tmp_path / "forces.csv"), "--no-drift-tracking"]) == 0
    assert "creep: not compensated" in capsys.readouterr().err
    est, true = read_forces(tmp_path / "forces.csv"), read_forces(out / "truth.csv")
    np.testing.assert_allclose(est, res["default_forces"], rtol=1e-8, atol=1e-8)  # forces file: 9 digits
    ang, mag = scenes.errors(est, true)
    d = next(r for r in _rows(out / "table.csv") if r["setting"] == "default")
    for key, vals, q in (("angle_med_deg", ang, 0.5), ("angle_p90_deg", ang, 0.9),
                         ("mag_err_med_n", mag, 0.5), ("mag_err_p90_n", mag, 0.9)):
        assert float(d[key]) == pytest.approx(float(np.quantile(vals, q)), rel=1e-7, abs=1e-7), key
    # with the unrounded forces the table's numbers are reproduced to 1e-9
    ang0, mag0 = scenes.errors(res["default_forces"], true)
    assert float(d["angle_med_deg"]) == pytest.approx(float(np.median(ang0)), abs=1e-9)
    assert float(d["mag_err_med_n"]) == pytest.approx(float(np.median(mag0)), abs=1e-9)


def test_render_pngs(tmp_path, capfd):
    """The pictures, and no VTK warning on stderr off screen (before: an ANSI-coloured 'bad X server
    connection. DISPLAY=' per window, written by VTK's own logger on file descriptor 2)."""
    import matplotlib.image as mpimg

    from cstomo_sensor.tools import render

    scene = tmp_path / "one.yaml"
    scene.write_text("sensor: cuboid_joint\nsnr_db: 60\nseed: 11\ntruth_mesh_size: 0.003\n"
                     "mechanics_mesh_size: 0.004\nloads:\n"
                     "  - {socket: {magnitude: 20, elevation_deg: 90, azimuth_deg: 0}}\n")
    paths = render.render("cuboid_joint", tmp_path / "png", scene, say=lambda msg: None)
    names = sorted(p.name for p in paths)
    assert names == ["load0_iso.png", "load0_slices.png", "mesh.png", "voltages.png"]
    for p in paths:
        img = mpimg.imread(p)
        panels = 3 if p.name.startswith("load") else 2  # truth, EIT image, scene field (a socket load)
        assert img.shape[:2] == (render.WINDOW[1], render.WINDOW[0] + 600 * (panels - 2)), p
        assert img[..., :3].std() > 0.01, f"{p} is blank"
    err = capfd.readouterr().err
    assert "bad X server" not in err and "\x1b[" not in err, err
