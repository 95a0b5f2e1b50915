"""``cstomo render``: off-screen pictures (pyvista, matplotlib) of a sensor and a scene.

One PNG per view, ``WINDOW`` pixels (600 wider per panel beyond two):

- ``mesh.png``: the reconstruction model's forward mesh with its electrode patches coloured;
- per socket load i of the scene (default ``scenes/cuboid_planar_60db.yaml``: 20 N at the paper's
  30, 90 and 120 degrees in the x-z plane), side by side, in kPa on one colour scale: the truth's
  mean stress K theta (independent truth mesh, the truth's mechanics) and the EIT image's mean
  stress (the default pipeline's field of the honest noisy frame, voxel values shown on the
  forward cells they hold), and the scene's own field (the mechanics' field of the estimated force,
  ``~/scene_stress_field``, at the same voxels):
  ``load{i}_iso.png`` (iso-surfaces at 25/50/75 % of each field's own maximum) and
  ``load{i}_slices.png`` (horizontal slices at z = 5, 10, 15 mm and the vertical section y = 0);
- ``voltages.png``: the 208 voltages of the unloaded and loaded frames, and their differences.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from ..angles import planar_angle
from ..errors import ConfigError, CstomoError, ModelMismatchError
from ..frame_path.config import PipelineConfig
from ..frame_path.pipeline import Pipeline
from ..inverse.reconstruction import voxel_basis
from ..model.geometry import load_sensor
from ..model.material import pressure_of_theta
from ..model.mesh import MeshSpec, build_mesh, electrode_patches
from ..model.simulate import Scene, add_noise
from .common import ToolParser, add_setting_arg, help_text

WINDOW = (1200, 600)
DEFAULT_SCENE = Path(__file__).resolve().parents[2] / "scenes" / "cuboid_planar_60db.yaml"


def _grid(points: np.ndarray, tets: np.ndarray, **cell_data):
    import pyvista as pv  # heavy (VTK): only where a surface is made or rendered

    cells = np.hstack([np.full((len(tets), 1), 4), tets]).ravel()
    g = pv.UnstructuredGrid(cells, np.full(len(tets), pv.CellType.TETRA, dtype=np.uint8), points * 1e3)
    for k, v in cell_data.items():
        g.cell_data[k] = np.asarray(v, float)
    return g


def _plotter(shape=(1, 2)):
    import pyvista as pv  # heavy (VTK): only where a surface is made or rendered
    from vtkmodules.vtkCommonCore import vtkLogger

    # off screen, VTK's logger warns once per window that it has no X display ('bad X server
    # connection. DISPLAY=', ANSI-coloured): nothing a user can act on; its errors still show
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_ERROR)
    pv.OFF_SCREEN = True
    size = [WINDOW[0] + 600 * max(0, shape[1] - 2), WINDOW[1]]
    p = pv.Plotter(off_screen=True, window_size=size, shape=shape, border=False)
    p.set_background("white")
    return p


def _view(p) -> None:
    p.camera_position = [(70.0, -95.0, 75.0), (0.0, 0.0, 9.0), (0.0, 0.0, 1.0)]
    p.camera.zoom(1.05)


def render_mesh(mesh, patches, out: Path) -> Path:
    import matplotlib  # heavy: only when a picture is drawn
    import pyvista as pv  # heavy (VTK): only where a surface is made or rendered

    p = _plotter((1, 1))
    p.add_mesh(_grid(mesh.points, mesh.tets).extract_surface(algorithm="dataset_surface"), color="lightgrey", show_edges=True,
               edge_color="grey", line_width=0.5)
    cmap = matplotlib.colormaps["tab20"]
    for i, pa in enumerate(patches):
        tri = np.unique(np.sort(pa.nodes, axis=1), axis=0)
        faces = np.hstack([np.full((len(tri), 1), 3), tri]).ravel()
        surf = pv.PolyData(mesh.points * 1e3, faces).clean()
        c = surf.points.mean(axis=0)
        out_dir = np.array([c[0], c[1], 0.0])
        out_dir = np.where(np.abs(out_dir) >= np.abs(out_dir).max() - 1e-9, np.sign(out_dir), 0.0)
        surf.points += 0.15 * out_dir  # lift the patch off the face (no z-fighting)
        p.add_mesh(surf, color=cmap(i % 20)[:3], show_edges=False)
        p.add_point_labels([c + 2.0 * out_dir], [f"e{i + 1}"], font_size=11, point_size=1,
                           shape_opacity=0.0, text_color="black")
    p.add_text(f"forward mesh: {mesh.n_nodes} nodes, {mesh.n_cells} tetrahedra; 16 electrode patches (mm)",
               font_size=10, color="black")
    p.show_axes()
    _view(p)
    path = out / "mesh.png"
    p.screenshot(str(path))
    p.close()
    return path


def _bar(title: str) -> dict:
    unit = title.split(",")[1].split()[0].rstrip(";") if "," in title else ""
    return {"title": unit, "color": "black", "vertical": True, "position_x": 0.85, "position_y": 0.1,
            "height": 0.7, "width": 0.08, "title_font_size": 14, "label_font_size": 12, "fmt": "%.0f"}


def _iso(p, g, name, title, cmap, lim):
    vmax = float(np.max(g.cell_data[name]))
    pg = g.cell_data_to_point_data()
    p.add_mesh(g.extract_surface(algorithm="dataset_surface").extract_feature_edges(30.0), color="grey")
    if vmax > 0:
        iso = pg.contour([0.25 * vmax, 0.5 * vmax, 0.75 * vmax], scalars=name)
        if iso.n_points:
            p.add_mesh(iso, scalars=name, cmap=cmap, clim=[0, lim], opacity=0.6,
                       scalar_bar_args=_bar(title))
    p.add_text(title + "  (iso 25/50/75 % of max)", font_size=9, color="black")
    _view(p)


def _slices(p, g, name, title, cmap, lim):
    pg = g.cell_data_to_point_data()
    for z in (5.0, 10.0, 15.0):
        p.add_mesh(pg.slice(normal="z", origin=(0, 0, z)), scalars=name, cmap=cmap, clim=[-lim, lim],
                   lighting=False, scalar_bar_args=_bar(title))
    p.add_mesh(pg.slice(normal="y", origin=(0, 0, 0)), scalars=name, cmap=cmap, clim=[-lim, lim],
               lighting=False, show_scalar_bar=False)
    p.add_mesh(g.extract_surface(algorithm="dataset_surface").extract_feature_edges(30.0), color="grey")
    p.add_text(title + "  (z = 5, 10, 15 mm; y = 0)", font_size=9, color="black")
    _view(p)


def render_case(panels: list[tuple], out: Path, i: int) -> list[Path]:
    """One picture per kind with a panel per ``(grid, title)``, every grid holding ``pressure_kPa``, on
    one colour scale: +-(the largest panel's 99.5 % quantile of |value|; the contact's peak would
    wash out the rest)."""
    lim = max(float(np.quantile(np.abs(g.cell_data["pressure_kPa"]), 0.995)) for g, _ in panels) or 1.0
    paths = []
    for kind, fn in (("iso", _iso), ("slices", _slices)):
        p = _plotter((1, len(panels)))
        for j, (grid, title) in enumerate(panels):
            p.subplot(0, j)
            vmax = float(np.max(grid.cell_data["pressure_kPa"]))
            fn(p, grid, "pressure_kPa", f"{title}; max {vmax:.0f} kPa", "coolwarm" if kind == "slices" else "viridis", lim)
        p.link_views()
        path = out / f"load{i}_{kind}.png"
        p.screenshot(str(path))
        p.close()
        paths.append(path)
    return paths


def render_voltages(ref: np.ndarray, frames: np.ndarray, labels: list[str], out: Path) -> Path:
    import matplotlib  # heavy: only when a picture is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: only when a picture is drawn

    fig, (a, b) = plt.subplots(1, 2, figsize=(WINDOW[0] / 100, WINDOW[1] / 100), dpi=100)
    k = np.arange(1, len(ref) + 1)
    a.plot(k, ref * 1e3, "k-", lw=1.2, label="unloaded (reference)")
    for f, lab in zip(frames, labels):
        a.plot(k, f * 1e3, lw=0.8, label=lab)
        b.plot(k, (f - ref) * 1e3, lw=0.8, label=lab)
    a.set_title("the 208 voltages")
    b.set_title("loaded minus unloaded")
    for ax in (a, b):
        ax.set_xlabel("measurement (docs/physics.md order)")
        ax.set_ylabel("mV")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    path = out / "voltages.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def render(sensor: str, out: str | Path, scene_path: str | Path | None = None, cache_dir=None,
           say=print) -> list[Path]:
    """Render every view; returns the PNG paths."""

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    scene = Scene.load(scene_path or DEFAULT_SCENE)
    geometry = load_sensor(sensor)
    if load_sensor(scene.sensor).name != geometry.name:
        raise ConfigError(f"scene is for sensor {scene.sensor!r}, not {sensor!r}")
    cfg = PipelineConfig(sensor=sensor, cache_dir=cache_dir or "")
    pipe = Pipeline.build(cfg)
    mesh = build_mesh(geometry, MeshSpec(h=cfg.mesh_size), cache_dir)
    cell_voxel, _, _ = voxel_basis(geometry, mesh, cfg.grid)
    if cell_voxel.max() + 1 != pipe.model.n_cells:
        raise ModelMismatchError(f"mesh gives {cell_voxel.max() + 1} voxels, the model {pipe.model.n_cells}: rebuild the cache")
    paths = [render_mesh(mesh, electrode_patches(mesh, geometry), out)]
    say(f"wrote {paths[-1]}")
    # the scene, simulated exactly as `cstomo simulate` does (frames_per_load = 1 per load)
    truth = scene.truth(cache_dir)
    rng = np.random.default_rng(scene.seed + 1)
    ref = add_noise(truth.reference, truth.reference, scene.snr_db, rng)
    pipe.set_reference(ref)
    tm = truth.forward.mesh
    frames, labels = [], []
    for i, load in enumerate(scene.loads):
        if load.kind != "socket":
            say(f"load {i}: {load.kind} (not a socket load): skipped")
            continue
        v = add_noise(truth.voltages(load), truth.reference, scene.snr_db, rng)
        f = load.force_vector
        label = f"{np.linalg.norm(f):.0f} N at {np.degrees(planar_angle(f)):.0f} deg"
        res = pipe.process(v, with_field=True)
        if not res.valid:
            say(f"load {i}: implausible frame ({res.reason}): skipped")
            continue
        pressure = pressure_of_theta(truth.theta(load), geometry.material)
        est = f"{res.magnitude:.1f} N, estimated at {np.degrees(planar_angle(res.force)):.0f} deg"
        panels = [(_grid(tm.points, tm.tets, pressure_kPa=pressure * 1e-3), f"truth mean stress, kPa; {label}"),
                  (_grid(mesh.points, mesh.tets, pressure_kPa=res.field.pressure[cell_voxel] * 1e-3),
                   f"EIT image mean stress, kPa; {est}")]
        if res.scene_field is not None:  # the mechanics' field of the estimated force, at the image's voxels
            panels.append((_grid(mesh.points, mesh.tets, pressure_kPa=res.scene_field.pressure[cell_voxel] * 1e-3),
                           f"scene field mean stress, kPa; {est}"))
        paths += render_case(panels, out, i)
        say(f"wrote {paths[-2]}, {paths[-1]} ({label}; estimate {est})")
        frames.append(v)
        labels.append(label)
    paths.append(render_voltages(ref, np.array(frames), labels, out))
    say(f"wrote {paths[-1]}")
    return paths


def parser() -> argparse.ArgumentParser:
    """This command's argument parser (cli.subcommand_parser)."""
    p = ToolParser(prog="cstomo render", description=help_text(__doc__.splitlines()[0]))
    add_setting_arg(p, "sensor")
    p.add_argument("--out", required=True, help="output directory for the PNGs")
    p.add_argument("--scene", default=None, help=f"scene file (default {DEFAULT_SCENE.name})")
    add_setting_arg(p, "cache_dir")
    return p


def main(argv: list[str] | None = None) -> int:
    a = parser().parse_args(sys.argv[1:] if argv is None else argv)
    try:
        render(a.sensor, a.out, a.scene, a.cache_dir or None)
    except (CstomoError, OSError) as err:
        print(f"cstomo render: error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
