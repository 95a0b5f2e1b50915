"""The benchmark's outputs: CSV files, the markdown table and the speed/accuracy trade curve."""
from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ...settings import DEFAULT_SENSOR


def pareto(times: np.ndarray, errs: np.ndarray) -> np.ndarray:
    """Boolean mask of the settings no other setting beats on both time and error."""
    n = len(times)
    front = np.ones(n, bool)
    for i in range(n):
        for j in range(n):
            if j != i and times[j] <= times[i] and errs[j] <= errs[i] and (times[j] < times[i] or errs[j] < errs[i]):
                front[i] = False
    return front


def write_csv(path: Path, rows: list[dict], cols: list[str]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: (repr(v) if isinstance(v, float) else v) for k, v in r.items()})


def write_rows(path: Path, rows: list[dict], say) -> list[dict]:
    """``rows`` (dicts with the same keys) to the CSV file ``path`` and, as a markdown table, to ``say``."""
    cols = list(rows[0])
    write_csv(path, rows, cols)
    say("| " + " | ".join(cols) + " |\n|" + "---|" * len(cols))
    for r in rows:
        say("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in r.values()) + " |")
    return rows


MD_COLS = [("setting", "setting", "{}"), ("grid", "grid", "{}"), ("basis", "basis", "{}"), ("k", "iterations", "{}"),
           ("p", "weight_power", "{:g}"),
           ("n_vox", "n_voxels", "{}"), ("build s", "build_s", "{:.1f}"), ("build MB", "build_mem_mb", "{:.0f}"),
           ("frame ms (med/p99)", None, None), ("estimator ms (med/p99)", None, None), ("fps", "fps", "{:.0f}"),
           ("angle deg (med/p90)", None, None), ("|F| err N (med/p90)", None, None),
           ("image corr", "img_corr_med", "{:.2f}"), ("peak dist mm", "peak_dist_med_mm", "{:.1f}")]


def markdown(rows: list[dict]) -> str:
    head = "| " + " | ".join(c[0] for c in MD_COLS) + " |"
    lines = [head, "|" + "---|" * len(MD_COLS)]
    for r in rows:
        cells = []
        for title, key, fmt in MD_COLS:
            if key:
                cells.append(fmt.format(r[key]))
            elif title.startswith("frame"):
                cells.append(f"{r['frame_med_ms']:.3f} / {r['frame_p99_ms']:.3f}")
            elif title.startswith("estimator"):
                cells.append(f"{r['estimator_med_ms']:.3f} / {r['estimator_p99_ms']:.3f}")
            elif title.startswith("angle"):
                cells.append(f"{r['angle_med_deg']:.2f} / {r['angle_p90_deg']:.2f}")
            else:
                cells.append(f"{r['mag_err_med_n']:.2f} / {r['mag_err_p90_n']:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _labels(ax, rows, x, y) -> None:
    """Annotate points; labels of points that sit on top of each other are stacked."""
    placed: list[tuple[float, float, int]] = []
    lx, ly = np.log10(x), np.asarray(y, float)
    span = max(float(np.ptp(ly[np.isfinite(ly)])) if np.isfinite(ly).any() else 1.0, 1e-9)
    for r, a, b, xa, yb in zip(rows, lx, ly, x, y):
        n = sum(1 for (pa, pb, _) in placed if abs(pa - a) < 0.12 and abs(pb - b) < 0.04 * span)
        placed.append((a, b, n))
        ax.annotate(r["setting"], (xa, yb), textcoords="offset points", xytext=(6, 4 - 10 * n), fontsize=7)


def plot_tradeoff(rows: list[dict], path: Path) -> None:
    import matplotlib  # heavy: only when a picture is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # heavy: only when a picture is drawn

    t = np.array([r["frame_med_ms"] for r in rows])
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), dpi=90)
    for ax, key, label in ((axes[0], "angle_med_deg", "force angle error, median deg"),
                           (axes[1], "img_corr_med", "image error: 1 - correlation with truth, median")):
        e = np.array([r[key] for r in rows], float)
        if key == "img_corr_med":
            e = 1.0 - e
        front = pareto(t, e)
        ax.scatter(t, e, c="tab:blue", zorder=3, label="setting (one knob varied)")
        o = np.argsort(t[front])
        ax.step(t[front][o], e[front][o], where="post", c="tab:red", lw=1.5, zorder=2, label="Pareto front")
        ax.scatter(t[front], e[front], facecolors="none", edgecolors="tab:red", s=120, zorder=4)
        d = [i for i, r in enumerate(rows) if r["setting"] == "default"]
        ax.scatter(t[d], e[d], marker="*", s=260, c="gold", edgecolors="k", zorder=5, label="default")
        _labels(ax, rows, t, e)
        ax.set_xscale("log")
        ax.set_xlabel("per-frame time: process(frame, with_field=True), median ms, one core")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(loc="upper right", fontsize=7)
    fig.suptitle(f"{DEFAULT_SENSOR}: accuracy against speed (held-out honest scenes, 60 dB)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
