"""``cstomo bench --drift --robot``, issue 34 item 6: the full change of a device over time on devices outside
the model.

robot.py's loaded warm-up and restarts change the rubber uniformly (the tracker's own direction). Here the
device changes as a temperature change moves a real block (model/timeline.py :func:`full_change`): the
rubber's mean resistivity by :data:`CHANGE` (+-2.4 %: 3 K at 0.8 %/K), +-30 % of it across the block along
x (:data:`GRADIENT`), every contact following its own temperature at -1 %/K (-3 % at +2.4 %, +3 % at
-2.4 %). On each of :data:`FULL_SCENES` (device_b, robot.py's least sensitive corner, and device_c, a third
device at neither corner: another rubber batch with an electrode re-seated, 45 dB), calibrated and tared
unchanged as in robot.py, with the truth from its own mesh:

a. ``full loaded warm-up``: the change reached linearly over 5 minutes while robot.py's socket loads follow
   each other without rest (the same loads, seed and rate as its loaded warm-up), against the same loads
   on the unchanged device (``full: loaded, unchanged``); the aim: the last minute within 1.5 x angle /
   1.6 x magnitude of the unchanged device's.
b. ``full restart at rest +-2.4 %``: the node restarts from a tare file :data:`AGE_S` old (8 hours: the
   node's own start, robot.py :func:`~.robot.restarted_stream`: the file's age widens the tracker's
   states) on the changed device, unloaded for 20 s; against the same restart of the unchanged device
   (``+0 %``); the aim: the zero's p99 from 1 s within 1.25 x of the unchanged device's.
c. ``full restart loaded +-2.4 %``: the same restart with the joint loaded from the first frame (robot.py's
   loaded restart: loads back to back, 3 s each, 60 s); the aim: from 5 s within 1.5 x / 1.6 x.

Every series both estimators, tracking on (the node's default), creep compensation off (the truth does not
creep). Besides robot.py's figures, each window's ``silent_pct``: the published frames "silently wrong"
(beyond the bounds of ``wrong_pct`` AND beyond 3 ``sigma_n``), over ``all`` frames from the first (the aim:
<= 1 % on every series). The rows go into robot.csv with the others; :func:`markdown` is robot.md's table.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np

from ...model import elasticity
from ...model.material import CONTACT_PER_K, RESISTIVITY_PER_K
from ...model.timeline import Timeline, full_change
from ...settings import ESTIMATORS
from . import robot
from .report import write_csv
from .scenes import SCENES

#: The devices judged: robot.py's device_b, and device_c at neither of robot.py's corners.
FULL_SCENES = (robot.DEVICE_SCENES[1], SCENES / "cuboid_device_c_45db.yaml")
CHANGE = 0.024              # the rubber's mean resistivity change (3 K at 0.8 %/K)
GRADIENT = 0.3              # +- of the mean change across the block (along x)
AGE_S = 8 * 3600.0          # b, c: the tare file is 8 hours old
WARM, WARM_STILL = "full loaded warm-up +2.4 % in 5 min", "full: loaded, unchanged"
#: (case, scenario of the changed device, of the unchanged one, window, figures, aims)
AIMS = (("warming while loaded", WARM, WARM_STILL, "last min", ("angle_deg", "magnitude_pct"), (1.5, 1.6)),
        ("restart at rest +2.4 %", "full restart at rest +2.4 %", "full restart at rest +0.0 %", "from 1 s",
         ("zero_p99_n",), (1.25,)),
        ("restart at rest -2.4 %", "full restart at rest -2.4 %", "full restart at rest +0.0 %", "from 1 s",
         ("zero_p99_n",), (1.25,)),
        ("restart loaded +2.4 %", "full restart loaded +2.4 %", "full restart loaded +0.0 %", "from 5 s",
         ("angle_deg", "magnitude_pct"), (1.5, 1.6)),
        ("restart loaded -2.4 %", "full restart loaded -2.4 %", "full restart loaded +0.0 %", "from 5 s",
         ("angle_deg", "magnitude_pct"), (1.5, 1.6)))
SILENT_AIM = 1.0            # % of published frames silently wrong, every series, from the first frame


#: The session before the restarts (s), at rest while the device takes the change: what a node running
#: before its restart learns the device's own directions from (force/slow_states/learned.py), saved beside its tare.
LEARN_S = 90.0


def robot_bench(out: str | os.PathLike, cache_dir=None, say=print) -> list[dict]:
    """``cstomo bench --drift --robot``: robot.py's rows on its :data:`~.robot.DEVICE_SCENES`, then this
    module's on :data:`FULL_SCENES`; one calibration per device. Writes robot.csv and robot.md in ``out``."""
    return _bench(out, robot.DEVICE_SCENES, "robot", cache_dir, say, LEARN_S)


def full_change_bench(out: str | os.PathLike, cache_dir=None, say=print, learn_s: float = LEARN_S) -> list[dict]:
    """This module's rows only (the lines of robot.md's last table, a third of the bench's time): writes
    robot_change.csv and robot_change.md in ``out``; ``learn_s``: :func:`full_change_rows`'s learning session."""
    return _bench(out, (), "robot_change", cache_dir, say, learn_s)


def _bench(out, robot_scenes, name: str, cache_dir, say, learn_s: float = 0.0) -> list[dict]:
    t_start = time.perf_counter()
    rows = []
    for scene in dict.fromkeys((*robot_scenes, *FULL_SCENES)):
        with elasticity.kept():  # the device's mechanics factorised once for its calibration and every timeline
            device = robot.prepare_device(scene, cache_dir, say)
            if scene in robot_scenes:
                rows += robot.device_rows(scene, cache_dir, say, device)
            if scene in FULL_SCENES:
                t0 = time.perf_counter()
                rows += full_change_rows(device, cache_dir, say, learn_s=learn_s)
                say(f"robot bench: the full change on {device[1].geometry.name}, {time.perf_counter() - t0:.0f} s")
            del device
    Path(out).mkdir(parents=True, exist_ok=True)
    write_csv(Path(out) / f"{name}.csv", rows, list(rows[0]))
    md = (robot.markdown(rows) + "\n" if robot_scenes else "") + markdown(rows)
    (Path(out) / f"{name}.md").write_text(md)
    say(md)
    say(f"robot bench: {time.perf_counter() - t_start:.0f} s")
    return rows


def change_spec(change: float, ramp_s: float, duration: float, tasks) -> object:
    """The module docstring's change (``change`` of the mean resistivity) at ``ramp_s`` (0: from the first frame)."""
    return full_change(change, GRADIENT, CONTACT_PER_K, RESISTIVITY_PER_K, ramp_s=ramp_s, duration=duration,
                       tasks=tasks)


def full_change_rows(device, cache_dir=None, say=print, estimators=ESTIMATORS, warm_s: float = robot.WARM_S,
                     restart_s: float = robot.RESTART_S, loaded_s: float = robot.RESTART_LOADED_S,
                     learn_s: float = 0.0) -> list[dict]:
    """Every series of the module docstring on ``device`` (robot.py :func:`~.robot.prepare_device`'s
    (scene, truth, pipes, tare)); ``warm_s``, ``restart_s``, ``loaded_s``: the scenarios' durations (a
    shorter run for the tests). ``learn_s`` > 0: before the restarts, a session of that many seconds from
    the tare at rest while the device takes the full change (+:data:`CHANGE`, reached at 2/3 of it) learns
    the device's own directions (force/slow_states/learned.py), and the restarts' tare file carries them (the node
    that ran before its restart); 0: none (a tare file without them)."""
    sc, truth, pipes, tare = device
    dev = truth.geometry.name
    rows = []

    def timeline(spec):
        return Timeline(spec, snr_db=sc.snr_db, seed=robot.SEED, cache_dir=cache_dir, truth=truth).prepare()

    def minutes(t):
        return [(f"min {m + 1}", (t >= 60 * m) & (t < 60 * (m + 1))) for m in range(int(np.ceil(warm_s / 60)))] + [
            ("last min", t >= warm_s - 60.0), ("all", t >= 0.0)]

    def restart_windows(after):
        return lambda t: [("first 1 s", t < 1.0), (f"from {after:g} s", t >= after), ("all", t >= 0.0)]

    series = [(WARM, change_spec(CHANGE, warm_s, warm_s, robot.socket_tasks(robot.SEED)), None, robot.LOADED_RATE,
               minutes),
              (WARM_STILL, _with_duration(robot.loaded_warmup(False), warm_s), None, robot.LOADED_RATE, minutes)]
    for loaded, duration, after in ((False, restart_s, 1.0), (True, loaded_s, 5.0)):
        tasks = robot.socket_tasks(robot.SEED + 1) if loaded else None
        for change in (CHANGE, -CHANGE, 0.0):
            spec = (change_spec(change, 0.0, duration, tasks) if change
                    else _with_duration(robot.restart(0.0, loaded), duration))  # unchanged: robot.py's own timeline
            series.append((f"full restart {'loaded' if loaded else 'at rest'} {100 * change:+.1f} %", spec, AGE_S,
                           robot.RATE, restart_windows(after)))
    learned = {name: None for name in estimators}
    if learn_s > 0:
        tl = timeline(change_spec(CHANGE, learn_s * 2 / 3, learn_s, None))
        for name in estimators:
            streams = []
            robot.run_stream(pipes[name], tl, tare, True, robot.RATE, 0.0, streams=streams)
            learned[name] = streams[0].slow.directions
            say(f"robot bench: {dev}, {name}: {len(learned[name])} direction(s) learned in {learn_s:g} s at rest")
    for scenario, spec, age, rate, windows in series:
        tl = timeline(spec)
        for name in estimators:
            times, est, forces, scale, sigma = robot.run_stream(pipes[name], tl, tare, True, rate, 0.0,
                                                                tare_file_age=age,
                                                                directions=learned[name] if age else None)
            for label, sel in windows(times):
                rows.append({"scenario": scenario, "device": dev, "estimator": name, "tracking": True, "window": label,
                             **robot.window_errors(est, forces, scale, sel, sigma)})
            r = rows[-1]
            say(f"robot bench: {dev}, {scenario}, {name}: all frames err {r['err_n']:.3f} N, silently wrong "
                f"{r['silent_pct']:.2f} %, > 3 sigma {r['over3sigma_pct']:.2f} %, tracked {r['tracked_change']:+.4f}")
    return rows


def _with_duration(spec, duration: float):
    return spec if spec.duration == duration else type(spec)(**{**spec.__dict__, "duration": duration})


def aim_figures(rows: list[dict], dev: str, est: str) -> list[dict]:
    """Per case of :data:`AIMS` on device ``dev`` with estimator ``est``: the changed and the unchanged
    device's figures, their ratios, whether the aims hold, and both series' silently wrong share (all frames)."""
    def find(scenario, window):
        return next((r for r in rows if (r["device"], r["scenario"], r["estimator"], r["window"])
                     == (dev, scenario, est, window)), None)

    out = []
    for case, changed, still, window, keys, aims in AIMS:
        c, u, ca, ua = find(changed, window), find(still, window), find(changed, "all"), find(still, "all")
        if not all((c, u, ca, ua)):
            continue
        ratios = [c[k] / u[k] if u[k] > 0 else np.nan for k in keys]
        first = find(changed, "first 1 s")
        out.append({"case": case, "window": window, "changed": [c[k] for k in keys], "unchanged": [u[k] for k in keys],
                    "ratios": ratios, "aims": aims, "met": all(r <= a for r, a in zip(ratios, aims)),  # NaN (every frame refused): missed
                    "first_s_err_n": first["err_n"] if first else np.nan,
                    "silent_pct": (ca["silent_pct"], ua["silent_pct"]),
                    "over3sigma_pct": (ca["over3sigma_pct"], ua["over3sigma_pct"]),
                    "implausible": (ca["implausible"], ua["implausible"]), "tracked_change": c["tracked_change"]})
    return out


def markdown(rows: list[dict]) -> str:
    """robot.md's table of the full change (issue 34): per device, estimator and case."""
    devices = list(dict.fromkeys(r["device"] for r in rows if r["scenario"].startswith("full")))
    lines = ["The full change (issue 34): +-2.4 % resistivity, a 30 % gradient, contacts -1 %/K; tracking on; "
             "changed / unchanged device (ratio, [aim]); silently wrong: beyond 0.5 N or 10 % AND beyond "
             "3 sigma_n, all frames from the first, changed / unchanged", "",
             "| device | estimator | case | window | figure | changed / unchanged (ratio) [aim] | first 1 s err N "
             "| silently wrong % | > 3 sigma % | implausible | tracked change |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for dev in devices:
        for est in ESTIMATORS:
            for f in aim_figures(rows, dev, est):
                keys = next(a[4] for a in AIMS if a[0] == f["case"])
                fig = " / ".join({"angle_deg": "angle deg", "magnitude_pct": "magnitude %",
                                  "zero_p99_n": "zero p99 N"}[k] for k in keys)
                vals = " ; ".join((f"{c:.2f}" if np.isfinite(c) else "refused") + f" / {robot._f(u)}"
                                  + (f" ({r:.2f} x)" if np.isfinite(r) else "") + f" [{a:g}]"
                                  for c, u, r, a in zip(f["changed"], f["unchanged"], f["ratios"], f["aims"]))
                lines.append(f"| {dev.replace('cuboid_joint_', '')} | {est} | {f['case']} | {f['window']} | {fig} | "
                             f"{vals}{'' if f['met'] else ' (missed)'} | {robot._f(f['first_s_err_n'])} | "
                             f"{robot._f(f['silent_pct'][0])} / {robot._f(f['silent_pct'][1])} | "
                             f"{robot._f(f['over3sigma_pct'][0], '.1f')} / {robot._f(f['over3sigma_pct'][1], '.1f')} | "
                             f"{f['implausible'][0]} / {f['implausible'][1]} | {f['tracked_change']:+.4f} |")
    return "\n".join(lines) + "\n"
