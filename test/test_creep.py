"""Creep (force/slow_states/creep.py): a held load reads constant, its recovery reads zero, the coefficient is fitted
from a held load and carried by the calibration file. The data: the honest device over time
(model/timeline.py: its own mesh, the creep law applied to the truth's strain), never the model's."""
from __future__ import annotations

import functools

import numpy as np
import pytest

from cstomo_sensor.force.slow_states.creep import CREEP_T0, creep_kernel


def test_a_stamp_that_goes_back_or_jumps_does_not_corrupt_the_history():
    """A held change (1 per channel) at 100 frames/s; the clock stepped back by 5 s or ahead by 30 s at
    0.51 s (from then on), or one frame's stamp off by as much: the creep offset afterwards stays within
    3e-3 of the clean run's (the history ages by at most 10 frame periods at the step; unguarded, the
    frame after a stamp 5 s early aged it by 5 s: 0.04)."""
    from cstomo_sensor.force.slow_states.creep import CreepCompensator

    runs = {}
    cases = [("clean", 0.0, False)] + [(f"{d:+g} s {kind}", d, kind == "once") for d in (-5.0, 30.0)
                                       for kind in ("step", "once")]
    for name, d, once in cases:
        c = CreepCompensator(0.04, 3)
        out = []
        for k in range(1000):
            t = 0.01 * k + (d if (k == 51 if once else k >= 51) else 0.0)
            c.observe(np.ones(3) - c.offset, t)
            out.append(c.offset[0])
        runs[name] = np.array(out)
    for name, *_ in cases[1:]:
        assert np.max(np.abs(runs[name][60:] - runs["clean"][60:])) < 3e-3, (name, np.max(np.abs(runs[name][60:] - runs["clean"][60:])))


def test_the_kernel_is_the_documented_law():
    """The kernel against log10(max(t, 0.1) / 0.1) written out here: zero until 0.1 s (the law is flat
    there), then within 0.003 of a decade to 1e5 s (0.012 % of a load at 4 % per decade); the former
    kernel, without the delay, ran up to 0.17 of a decade ahead within 0.2 s of a change."""
    t = np.concatenate([np.linspace(0.0, 0.1, 11), np.logspace(-1, 5, 600)])
    law = np.log10(np.maximum(t, 0.1) / 0.1)
    assert np.max(np.abs(creep_kernel(t) - law)) < 0.003
    assert np.all(creep_kernel(t[t <= 0.1]) == 0.0)
    assert CREEP_T0 == 0.1


@pytest.mark.parametrize("rate, jitter", [(10.0, 0.0), (100.0, 0.0), (25.0, 0.0), (100.0, 20e-6)])
def test_a_held_change_that_creeps_by_the_law_is_compensated_from_its_first_frame(rate, jitter):
    """A change of 1 that creeps at 4 % per decade by the law itself (from the frame that shows it),
    held 10 minutes and removed: compensated within 0.08 % of it at every frame from its first (0.66 %
    with the former kernel), 0.02 % after its removal, at 10, 100 and 25 frames/s, and with stamps
    that jitter by 20 us as a board's mapped to the host's clock do."""
    from cstomo_sensor.force.slow_states.creep import CreepCompensator

    c = 0.04
    t = np.arange(0.0, 620.0, 1.0 / rate)
    t += np.random.default_rng(3).uniform(-jitter, jitter, len(t))
    on, off = t[np.searchsorted(t, 1.0 - 1e-9)], t[np.searchsorted(t, 601.0 - 1e-9)]
    phi = lambda tau: np.where(tau >= 0, np.log10(np.maximum(tau, 0.1) / 0.1), 0.0)  # noqa: E731
    measured = (t >= on) * 1.0 - (t >= off) * 1.0 + c * (phi(t - on) - phi(t - off))
    comp = CreepCompensator(c, 2)
    out = np.empty_like(t)
    for k in range(len(t)):
        y = measured[k] - comp.offset
        out[k] = y[0]
        comp.observe(y, t[k])
    truth = ((t >= on) & (t < off)) * 1.0
    assert np.max(np.abs(out - truth)) < 8e-4, (t[np.argmax(np.abs(out - truth))], np.max(np.abs(out - truth)))
    assert np.max(np.abs(out[t >= off])) < 2e-4


@functools.cache
def _device():
    """The honest device of every timeline here (cuboid_joint, seed 31, its own 3 mm mesh), one object: a
    load's mechanics solved for one timeline serve the next (the 20 N hold's for every rubber's creep),
    instead of one factorisation of the elasticity per timeline. Each timeline is the one its sensor
    name and seed make (the same cache entry)."""
    from cstomo_sensor.model.geometry import load_sensor
    from cstomo_sensor.model.simulate import Truth

    return Truth(load_sensor("cuboid_joint"), seed=31)


def _held(warm_model, snr_db):
    from cstomo_sensor.model.timeline import Timeline, held_load_creep

    assert warm_model.geometry.name == "cuboid_joint"
    tl = Timeline(held_load_creep(20.0, creep=0.04, on=1.0, off=601.0, duration=631.0), snr_db=snr_db, seed=31,
                  truth=_device()).prepare()
    rng = np.random.default_rng(7)
    times, frames, forces, _ = tl.frames(10.0, rng=rng)
    return times, frames, tl.tare(20, rng)


@pytest.fixture(scope="module")
def held(warm_model):
    """A 20 N load pressed into the socket at 1 s, held 10 minutes, removed; 10 frames/s, 60 dB, creep 4 %."""
    return _held(warm_model, 60)


def _magnitudes(pipe, held, creep, tracking=True):
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream

    times, frames, tare = held
    stream = FrameStream(pipe, StreamConfig.offline(drift_tracking=tracking, creep_per_decade=creep))
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1) if tare.std() > 0 else None, 20, "tare")
    mag = np.full(len(times), np.nan)
    for k, (t, v) in enumerate(zip(times, frames)):
        out = stream.push(v, stamp_ns=int(1e9 * (1 + t)))
        if out is not None and out.result.valid:
            mag[k] = out.result.magnitude
    return times, mag


def _readings(times, mag):
    """(1 s after the load was applied, its last 10 s, 5 s after its removal): medians."""
    return (np.nanmedian(mag[(times >= 1.9) & (times <= 2.1)]), np.nanmedian(mag[(times >= 590) & (times < 600.9)]),
            np.nanmedian(mag[(times >= 606) & (times <= 607)]))


@pytest.mark.slow
def test_a_held_load_reads_constant_and_its_recovery_reads_zero(warm_model, held):
    """The issue's aim: 20 N held 10 minutes reads within 1 % of its value 1 s after it was applied
    (uncompensated: 10 % more, the strain's 4 % per decade over 2.8 decades), and 5 s after its removal
    the rest reads at most 0.5 N (uncompensated 0.63 N, compensated 0.20-0.23 N: the noise's own floor,
    a magnitude of noise alone reads 0.17 N there on the same device without creep, docs/node.md#creep)."""
    rows = []
    for creep, tracking in ((0.04, True), (0.04, False), (0.0, True)):
        early, late, after = _readings(*_magnitudes(warm_model, held, creep, tracking))
        print(f"creep {creep}, tracking {tracking}: {early:.2f} N -> {late:.2f} N, 5 s after removal {after:.3f} N")
        rows.append((creep, tracking, early, late, after))
    uncompensated = rows[-1][4]
    for creep, _tracking, early, late, after in rows:
        if creep:
            assert abs(late / early - 1) < 0.01 and after <= 0.5 and after < 0.5 * uncompensated, rows
        else:
            assert late / early - 1 > 0.05 and after > 0.3, rows


@pytest.mark.slow
def test_without_noise_the_compensated_hold_is_flat_to_a_tenth_of_a_percent(warm_model):
    """The same hold without noise, tracking off (what the compensation alone does): 600 s against 1 s
    within 0.2 % (measured: -0.02 % with this `linear` pipeline, -0.09 % before the kernel followed the
    law from 0.1 s; the default `model` -0.09 %, before -0.17 %, of which -0.07 % is the change's
    non-linearity in the strain), and below 0.05 N at rest 5 s after the removal (measured 0.03 N; 1.7 N
    uncompensated)."""
    held = _held(warm_model, None)
    early, late, after = _readings(*_magnitudes(warm_model, held, 0.04, tracking=False))
    print(f"noise-free, compensated: {early:.3f} N -> {late:.3f} N ({100 * (late / early - 1):+.3f} %), "
          f"5 s after removal {after:.3f} N")
    assert abs(late / early - 1) < 0.002 and after < 0.05, (early, late, after)


@pytest.mark.slow
def test_the_coefficient_is_fitted_from_a_held_load_and_carried_by_the_calibration_file(warm_model, held, tmp_path):
    from cstomo_sensor.force.reference.calibration import DeviceCalibration
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream
    from cstomo_sensor.tools.calibrate import held_creep

    times, frames, tare = held
    warm_model.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1), 20)
    on = (times >= 1.0) & (times < 121.0)  # two minutes of the hold, from the load's application
    c = held_creep(warm_model, frames[on], 10.0)
    assert c == pytest.approx(0.04, rel=0.2), c
    cal = DeviceCalibration("cuboid_joint", "h", "linear", np.eye(3), np.zeros((208, 3)), creep_per_decade=c)
    cal.save(tmp_path / "cal.yaml")
    assert DeviceCalibration.load(tmp_path / "cal.yaml").creep_per_decade == pytest.approx(c, rel=1e-9)
    text = (tmp_path / "cal.yaml").read_text().replace(f"creep_per_decade: {c!r}", "creep_per_decade: 0.7")
    (tmp_path / "bad.yaml").write_text(text)
    from cstomo_sensor.errors import ConfigError
    with pytest.raises(ConfigError, match="creep_per_decade.*0.7"):
        DeviceCalibration.load(tmp_path / "bad.yaml")
    stream = FrameStream(warm_model, StreamConfig(creep_per_decade=0.02))
    assert stream.slow.creep_per_decade(stream.pipe.calibration) == 0.02  # no calibration: the setting, and the diagnostics say so
    assert "2.00% per decade, assumed" in stream.health(1e9)[2]["creep"]
    assert "not compensated" in FrameStream(warm_model, StreamConfig(creep_per_decade=0.0)).health(1e9)[2]["creep"]
    with pytest.raises(ValueError, match="decade of time"):
        held_creep(warm_model, frames[on][:50], 10.0)


@pytest.fixture(scope="module")
def recording(warm_model):
    """A calibration recording as the recipe asks for it, on the honest device creeping at 4 % per
    decade: 8 loads (8-30 N, elevations 30-90 deg) each held 6 s with 1 s unloaded between, 20
    frames/s, 60 dB; (tare, frames, applied forces)."""
    from cstomo_sensor.model.timeline import Timeline, TimelineSpec

    rng = np.random.default_rng(5)
    mag, el, az = rng.uniform(8, 30, 8), np.radians(rng.uniform(30, 90, 8)), rng.uniform(-np.pi, np.pi, 8)
    loads = np.column_stack([mag * np.cos(el) * np.cos(az), mag * np.cos(el) * np.sin(az), -mag * np.sin(el)])
    times, forces = [], []
    for k, f in enumerate(loads):
        times += [1.0 + 7.0 * k, 7.0 + 7.0 * k]
        forces += [tuple(f), (0.0, 0.0, 0.0)]
    spec = TimelineSpec(duration=57.0, creep=0.04, load_times=tuple(times), load_forces=tuple(forces))
    tl = Timeline(spec, snr_db=60, seed=31, truth=_device()).prepare()
    _, frames, applied, _ = tl.frames(20.0, rng=np.random.default_rng(3))
    return tl.tare(20, np.random.default_rng(4)), frames, applied


@pytest.mark.slow
def test_calibrate_fits_the_creep_from_the_recordings_held_loads_and_says_when_it_cannot(recording, tmp_path, capsys):
    """``cstomo calibrate --rate 20`` on the recording: the creep fitted on its 8 loads held 6 s is
    within 15 % of the truth's 4 % per decade (measured: 3.74 %; 3.6-4.2 % over five noise draws),
    written into the file (its rests, 0 N rows of the forces file, are the creep's history, not loads);
    without --rate (a frames file has no time), or with each load's frames listed for its first 3 s
    only (fewer than 3 held 5 s), it says why in one line and writes none; --creep-per-decade overrides."""
    from cstomo_sensor.force.reference.calibration import DeviceCalibration
    from cstomo_sensor.frames_io import write_forces, write_frames
    from cstomo_sensor.tools.calibrate import main

    tare, frames, applied = recording
    write_frames(tmp_path / "ref.csv", tare)
    write_frames(tmp_path / "frames.csv", frames)
    write_forces(tmp_path / "forces.csv", applied)
    write_frames(tmp_path / "short.csv", frames)
    t = np.arange(len(frames)) / 20.0
    since = (t - 1.0) % 7.0  # each load from 1 + 7 k s for 6 s: listed for its first 3 s only
    rows = np.flatnonzero((np.linalg.norm(applied, axis=1) == 0) | (since < 3.0))
    with open(tmp_path / "short_forces.csv", "w") as f:
        f.write("frame,fx,fy,fz\n" + "".join(f"{k},{x:.9g},{y:.9g},{z:.9g}\n" for k, (x, y, z) in zip(rows, applied[rows])))
    common = ["--mesh-size", "0.004", "--grid", "6", "6", "3", "--estimator", "linear", "--reference", str(tmp_path / "ref.csv")]
    runs = {"fit": ["--rate", "20"], "no rate": [], "given": ["--rate", "20", "--creep-per-decade", "0.03"],
            "short": ["--rate", "20"]}
    said = {}
    for name, extra in runs.items():
        f = "short" if name == "short" else "frames"
        forces = "short_forces" if name == "short" else "forces"
        assert main([*common, "--frames", str(tmp_path / f"{f}.csv"), "--forces", str(tmp_path / f"{forces}.csv"),
                     *extra, "--out", str(tmp_path / f"{name.replace(' ', '_')}.yaml")]) == 0
        said[name] = [line for line in capsys.readouterr().out.splitlines() if line.startswith("creep:")]
        assert len(said[name]) == 1, (name, said[name])
    c = DeviceCalibration.load(tmp_path / "fit.yaml").creep_per_decade
    assert c == pytest.approx(0.04, rel=0.15), said["fit"]
    assert "fitted on the 8 loads (or rests) of the recording held 5 s or more" in said["fit"][0]
    assert "no time: give --rate" in said["no rate"][0]
    assert "0 of its 17 loads and rests held 5 s or more (3 needed)" in said["short"][0], said["short"]
    for name in ("no rate", "short"):
        assert DeviceCalibration.load(tmp_path / f"{name.replace(' ', '_')}.yaml").creep_per_decade is None
    assert DeviceCalibration.load(tmp_path / "given.yaml").creep_per_decade == 0.03
    assert "as given" in said["given"][0]


# --- issue 26's aim, with the default estimator on the simulator's own mesh -------------------------

HOLD_ON, HOLD_OFF = 1.0, 601.0  # 20 N straight down applied at 1 s, held 10 minutes, released


@pytest.fixture(scope="module")
def default_pipe():
    """The default pipeline (`model` estimator, the node's and `cstomo estimate`'s)."""
    from cstomo_sensor.frame_path.config import PipelineConfig
    from cstomo_sensor.frame_path.pipeline import Pipeline

    return Pipeline.build(PipelineConfig())


def _schedule(name: str) -> np.ndarray:
    """Frame times (s) over 0..631 s: a constant rate, or 100 frames/s within 20 s of each change of
    load and 1 frame/s in between (600 s of hold for the cost of 5 s: the compensation must not
    depend on the frame period, nor on its changes)."""
    if name == "10/s":
        return np.arange(6310) / 10.0
    if name == "100/s":
        return np.arange(63100) / 100.0
    fast = np.arange(2100) / 100.0  # 0..21 s
    return np.concatenate([fast, np.arange(21.0, 595.0, 1.0), 595.0 + np.arange(3600) / 100.0])


def _hold(pipe, rubber: float, comp: float, times: np.ndarray, snr_db, seed: int = 0):
    """(reading 1 s after the load was applied (N), at 600 s relative to it - 1, rest 1 s and 5 s after
    its removal (N), at 60 s relative to the reading at 1 s - 1): the 20 N hold on the honest device
    creeping by ``rubber`` per decade (its own 3 mm mesh, the law applied to its strain), through a
    default stream compensating ``comp``. With
    noise the readings are medians over 0.1 s (1 s), the hold's last 10 s and 1 s (rests)."""
    from cstomo_sensor.frame_path.config import StreamConfig
    from cstomo_sensor.frame_path.stream import FrameStream
    from cstomo_sensor.model.simulate import add_noise
    from cstomo_sensor.model.timeline import Timeline, held_load_creep

    tl = Timeline(held_load_creep(20.0, creep=rubber, on=HOLD_ON, off=HOLD_OFF, duration=631.0), snr_db=snr_db,
                  seed=31, truth=_device()).prepare()
    rng = np.random.default_rng(seed)
    frames = add_noise(tl.voltages(times), tl.reference, snr_db, rng)
    tare = tl.tare(50, rng)
    stream = FrameStream(pipe, StreamConfig.offline(creep_per_decade=comp))
    stream.set_reference(tare.mean(axis=0), tare.std(axis=0, ddof=1) if snr_db else None, 50, "tare")
    mag = np.full(len(times), np.nan)
    for k, (t, v) in enumerate(zip(times, frames)):
        out = stream.push(v, stamp_ns=int(1e9 * (10.0 + t)))
        if out is not None and out.result.valid:
            mag[k] = out.result.magnitude

    def at(t, half):  # the frame at t without noise, else the median within +-half s
        near = np.abs(times - t) <= (half if snr_db else 1e-6)
        assert near.any(), t
        return float(np.nanmedian(mag[near]))

    first = at(HOLD_ON + 1.0, 0.05)
    held = mag[(times >= HOLD_OFF - 10) & (times < HOLD_OFF)]  # the hold's last 10 s (its last frame without noise)
    late = float(np.nanmedian(held) if snr_db else held[-1])
    return first, late / first - 1, at(HOLD_OFF + 1.0, 0.5), at(HOLD_OFF + 5.0, 0.5), at(HOLD_ON + 60.0, 2.0) / first - 1


@pytest.mark.slow  # 38 000 frames through the default stream (~25 s)
def test_a_held_load_reads_within_a_tenth_of_the_aim_at_any_frame_period(default_pipe):
    """Issue 26's creep aim without noise (what the compensation does; the drift tracking on, as by
    default): 20 N held 10 minutes on a rubber at 4 % per decade compensated at 4 % reads within 0.7 %
    of its reading 1 s after it was applied (aim 1 %; measured +0.11 %, at 60 s +0.17 %), and 5 s after
    its removal the rest reads below 0.1 N (aim 0.5 N; measured 0.03 N), the same within 0.1 % and 0.02 N at 10
    frames/s and at 100 frames/s near the changes with 1 frame/s in the hold (before the frame period
    was the median of the last steps, the 1/s hold read +0.5 % at 60 s against -0.05 %). A
    rubber at 2 or 6 % compensated at its own coefficient holds the same (+0.21 %, +0.01 %); uncompensated
    it reads +11.8 % and 1.5 N (+10.9 % and 1.7 N with the tracking off). A constant 100 frames/s (63 100 frames, two
    thirds of this test's cost before) is test_issue_26s_creep_aim_at_60_db's schedule, against the aim
    at three noise draws; here the periods 0.01, 0.1 and 1 s meet in the two schedules compared."""
    rows = {}
    for rubber, comp, sched in [(0.04, 0.04, "10/s"), (0.04, 0.04, "hold at 1/s"),
                                (0.02, 0.02, "hold at 1/s"), (0.06, 0.06, "hold at 1/s"), (0.04, 0.0, "hold at 1/s")]:
        rows[rubber, comp, sched] = r = _hold(default_pipe, rubber, comp, _schedule(sched), None)
        print(f"rubber {rubber:.0%}, compensated at {comp:.0%}, {sched}: {r[0]:.3f} N at 1 s, {100 * r[1]:+.2f} % "
              f"at 600 s ({100 * r[4]:+.2f} % at 60 s), rest {r[2]:.3f} N 1 s and {r[3]:.3f} N 5 s after the removal")
    for (rubber, comp, sched), (_, drift, _, rest5, _) in rows.items():
        if comp:
            assert abs(drift) < 0.007 and rest5 < 0.1, (rubber, comp, sched, rows)
        else:
            assert drift > 0.08 and rest5 > 0.2, rows  # the tracker takes part of the recovery for the device
    ref, r = rows[0.04, 0.04, "10/s"], rows[0.04, 0.04, "hold at 1/s"]
    assert abs(r[1] - ref[1]) < 0.001 and abs(r[4] - ref[4]) < 0.001, rows
    assert abs(r[2] - ref[2]) < 0.02 and abs(r[3] - ref[3]) < 0.02, rows


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_issue_26s_creep_aim_at_60_db(default_pipe, seed):
    """Issue 26's creep aim as a board sees it: 60 dB, 100 frames/s, every default (4 % compensated,
    the drift tracking on) on a rubber at 4 % per decade: the hold's last 10 s within 1 % of its
    reading 1 s after it was applied (a median over 0.1 s: 11 frames), the rest 5 s after its removal
    at most 0.5 N. Measured over six noise draws: -0.78 to +0.55 % (the drift tracker's rate during
    the hold; -0.13 to +0.08 % with the tracking off, docs/node.md#creep), rest 0.11-0.13 N."""
    first, drift, rest1, rest5, _ = _hold(default_pipe, 0.04, 0.04, _schedule("100/s"), 60, seed)
    print(f"seed {seed}: {first:.3f} N at 1 s, {100 * drift:+.2f} % at 600 s, rest {rest1:.3f} N 1 s and "
          f"{rest5:.3f} N 5 s after the removal")
    assert abs(drift) < 0.01 and rest5 <= 0.5, (first, drift, rest1, rest5)
