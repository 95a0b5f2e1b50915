"""The device's slow states since the tare: its drift and its creep, and the force's uncertainty they
leave. No ROS, no serial.

A stage of the frame stream (frame_path/stream.py). With each reference it makes a drift tracker
(:class:`~.drift.DriftTracker`, ``drift_tracking``: the device's slow uniform change and its gradient)
and a creep compensator (:class:`~.creep.CreepCompensator`, ``creep_per_decade`` or the calibration's);
frame by frame it follows them, and hands the pipeline what it takes as arguments: :attr:`SlowStates.scale`
(the voltages' uniform scale), :attr:`SlowStates.offset` (the drift's gradient and the creep, summed,
in y units) and :attr:`SlowStates.gradient` (the resistivity gradients' states, which the ``model``
estimator's response follows). Per frame (:meth:`SlowStates.observe`) it takes the frame's record (the
pipeline's ``FrameRecord``: its result, its change, whether the change is plausible, the estimator's fit
and what the pipeline made it with) and returns what it adds to the result, a :class:`Correction`
(the force the tracker's update corrects it to, its 1-sigma), which the stream applies; it neither
rewrites the result nor reads the pipeline then. It reads the pipeline (the reference, the estimator,
the mask) only when the stream tells it one of them changed (:meth:`SlowStates.reset`,
:meth:`SlowStates.masked`, :meth:`SlowStates.renoised`).
"""
from __future__ import annotations

import logging
import math
from typing import Any, NamedTuple, Protocol

import numpy as np

from ...model.material import RESISTIVITY_PER_K
from ..checks.consistency import change_noise
from ..checks.expected import ExpectedLoad, bounded
from ..estimators.scale_fit import JointScale, gradient_directions
from .creep import CreepCompensator
from .drift import DriftTracker
from .learned import AVG, DirectionLearner, Directions, empty
from .sigma import CREEP_REL_ASSUMED, CREEP_REL_FITTED, ForceSigma, misfit, relative_error

log = logging.getLogger(__name__)

#: The drift tracker's change (``|s - 1|``) beyond which a re-tare is advised, and beyond which it is
#: outside what it was validated for (``cstomo bench --drift``: uniform changes up to 10 %).
RETARE_ADVISED = 0.05
VALIDATED = 0.10
#: The diagnostics warn when the states only a rest measures (the contacts', the gradient's) leave more
#: than this many newtons (1-sigma) at zero load (:data:`~.drift.FOLLOW_SIGMA`).
UNMEASURED_N = 2.0


def force_map(estimator) -> np.ndarray | None:
    """The ``estimator``'s linear map of a change to a force (the drift tracker's rest bound)."""
    return getattr(getattr(estimator, "linear", estimator), "W", None)


class InUse(Protocol):
    """What the slow states read of what a pipeline makes its frames with (frame_path/pipeline.py ``InUse``:
    a value, replaced when any of it changes; the force layer does not import the frame path)."""

    estimator: Any
    calibration: Any
    keep: np.ndarray
    reference_frames: int
    consistency: Any


class Reference(Protocol):
    """What the slow states read of a pipeline when its reference changes (:meth:`SlowStates.reset`;
    frame_path/pipeline.py ``Pipeline``): the reference (volts; None: none), what a change is divided by,
    the reconstruction model (its contacts' and gradients' directions) and :class:`InUse`."""

    reference: np.ndarray | None
    y_scale: float
    model: Any
    n_meas: int
    in_use: InUse


class Frame(Protocol):
    """What the slow states read of a frame through the pipeline (frame_path/pipeline.py ``FrameRecord``)."""

    result: Any  # its FrameResult (read, never written)
    change: np.ndarray
    plausible: bool
    fit: Any
    in_use: InUse


class Correction(NamedTuple):
    """What the slow states add to a frame's result (:meth:`SlowStates.observe`): ``force`` the force
    corrected by the tracker's update of this frame (None: unchanged), ``sigma`` its per-axis 1-sigma
    (N; None: none, an implausible frame) and ``sigma_n`` the rms of its error's norm (N)."""

    force: np.ndarray | None
    sigma: tuple[float, float, float] | None
    sigma_n: float


#: A frame's :class:`Correction` when there is none (an implausible frame).
NO_CORRECTION = Correction(None, None, float("nan"))


class SlowStates:
    """The drift tracker (``config.drift_tracking``) and the creep compensator (``config.creep_per_decade``,
    0: off) of a pipeline's reference, the offset and scale they give, and the checks of a controller's
    expected load (:class:`~cstomo_sensor.force.checks.expected.ExpectedLoad`: a sensor of range ``max_force``, the stream ``config``'s
    ``frame_id`` and ``expected_wrench_tolerance``); ``directions``: the device's own directions it starts with
    (force/slow_states/learned.py: its calibration's; None: none), until a saved tare brings its own (:meth:`reset`)."""

    def __init__(self, n_meas: int, config, max_force: float = math.inf, directions: Directions | None = None) -> None:
        self.tracking = bool(config.drift_tracking)
        self.creep_setting = float(config.creep_per_decade)
        self.drift: DriftTracker | None = None  # made with each reference (tracking)
        self.creep: CreepCompensator | None = None  # made with each reference (creep_per_decade)
        self.scale = 1.0  # the pipeline's arguments for the next frame: the voltages' uniform scale
        self.offset: np.ndarray | None = None  # ... and the drift's and the creep's offsets, summed (y units)
        self.gradient: list | None = None  # ... and the resistivity gradients' states (force/estimators/scale_fit.py), 3 floats
        self._sum = np.zeros(n_meas)
        self._block, self._block_for = slice(0), None  # the gradients' block of the tracker (_offsets)
        self._gradients: np.ndarray | None = None  # the tracker's gradient directions (the model's)
        self._sigma: ForceSigma | None = None  # the force's uncertainty (force/slow_states/sigma.py), for _sigma_for
        self._sigma_for: tuple = (None,) * 4  # ... made for this estimator, tracker, creep and calibration
        self.sigma_source = ""  # where the calibration residual of the sigma comes from
        self._joint: JointScale | None = None  # the joint fit of force and scale (force/estimators/scale_fit.py), for _joint_for
        self._joint_for: DriftTracker | None = None
        # a controller's expected load, checked (force/checks/expected.py); the latest frame's per-axis 1-sigma for its check
        self.expected = ExpectedLoad(max_force, config.expected_wrench_tolerance, config.frame_id)
        self._frame_sigma: tuple | None = None
        self.age_s: float | None = None  # the reference is a saved tare this old (reset)
        # the device's own directions (force/slow_states/learned.py): its calibration's, learned from its rests, or read
        # with a saved tare; the device's, so kept over a re-tare; learned_new: a direction learned since the stream last
        # saved them
        self.directions: Directions = directions if directions is not None and len(directions) else empty(n_meas)
        self.learner: DirectionLearner | None = None
        self.learned_new = False
        self._known_rest = False  # the next frame is known to be unloaded (known_unloaded)
        self._expected_now = False  # the frame's joint measurement has a controller's expected load (_joint_scale)

    def creep_per_decade(self, calibration) -> float:
        """The creep compensated: the calibration's coefficient if it has one, else the setting's; a
        setting of 0 turns it off, over a calibration's too."""
        if not self.creep_setting:
            return 0.0
        fitted = getattr(calibration, "creep_per_decade", None) if calibration is not None else None
        return float(fitted) if fitted is not None else self.creep_setting

    def reset(self, pipe: Reference, age_s: float | None = None, directions: Directions | None = None) -> None:
        """A tracker and a compensator for the reference ``pipe`` has just set (none without one);
        ``age_s``: the reference is a saved tare this old (a restart), which widens the tracker's states;
        ``directions``: the device's own directions saved with it (force/slow_states/learned.py; None: those learned so far)."""
        if directions is not None:
            self.directions = directions
        self.drift = self.creep = None
        self.learner = None
        self._frame_sigma = None  # the previous reference's frames' sigma is not this one's (expected load)
        self.age_s = age_s  # the reference's age (a restart), for the diagnostics and the tests
        if pipe.reference is not None:
            in_use = pipe.in_use
            if self.tracking:
                if self._gradients is None:  # the contacts' change, then the resistivity's gradient
                    g = gradient_directions(pipe.model)
                    c = pipe.model.contact
                    self._gradients = g if c is None else np.vstack([c, g])
                self.drift = DriftTracker(pipe.reference / pipe.y_scale, self._gradients,
                                          change_noise(in_use.estimator.noise, in_use.reference_frames),
                                          in_use.keep.copy(), force_map(in_use.estimator),
                                          contacts=0 if pipe.model.contact is None else len(pipe.model.contact))
                if len(self.directions):  # the device's own directions: states after the model's
                    self.drift = self.drift.with_directions(self.directions.rows, self.directions.per_scale, 0.0)
                self.learner = DirectionLearner(pipe.n_meas, len(self.directions))
                if age_s is not None:
                    self.drift.widen(age_s)
            c = self.creep_per_decade(in_use.calibration)
            if c > 0:
                self.creep = CreepCompensator(c, pipe.n_meas)
        self.scale = 1.0
        self._offsets()

    def masked(self, in_use: InUse) -> None:
        """The pipeline's mask changed (``in_use``: its ``InUse`` now): the tracker (its state kept) over its channels."""
        if self.drift is not None:
            self.drift = self.drift.rebuilt(keep=in_use.keep.copy(), force_map=force_map(in_use.estimator))
            self._offsets()

    def renoised(self, in_use: InUse) -> None:
        """The pipeline's noise changed (``in_use``: its ``InUse`` now): the tracker (its state kept) with the change's noise."""
        if self.drift is not None:
            est = in_use.estimator
            self.drift = self.drift.rebuilt(noise=change_noise(est.noise, in_use.reference_frames), force_map=force_map(est))
            self._offsets()

    def observe(self, frame: Frame, t: float | None, frozen: np.ndarray | None) -> Correction:
        """A frame at ``t`` (s; None: 10 ms after the previous) through the pipeline (``frame``: its
        ``FrameRecord``): the tracker and the compensator follow its change (``frozen``: the excluded
        channels, the creep's history held there); returns what it adds to its result (:class:`Correction`:
        the force the tracker's update corrects it to, its 1-sigma)."""
        drift, creep, result, in_use = self.drift, self.creep, frame.result, frame.in_use
        self.expected.t_frame = t
        sig = creep_f = corrected = None
        valid, force = result.valid, result.force
        if valid:
            sig = self._sigma_model(in_use)
            if creep is not None:
                creep_f = sig.creep_force(creep.offset)  # the offset this frame was corrected by
        if frame.plausible and (drift is not None or creep is not None):  # beyond max_force too
            y = frame.change  # the change with the creep so far taken out: the load's and the drift's
            if drift is not None:
                # every frame measures the scale jointly with its force (force/estimators/scale_fit.py JointScale; a
                # controller's expected load sharpens it); the force follows the scale's update
                joint = self._joint_scale(frame, t)
                rest = drift.observe(y, t, joint, self._expected_now)  # (an expected load: the states updated now)
                self.scale = drift.scale
                if drift.force_step is not None and valid:
                    force = corrected = force + drift.force_step
                if self.learner is not None:
                    self._learn(y, rest, force if valid else None)
                    if drift is not self.drift:  # one more state: its sigma too
                        drift = self.drift
                        sig = self._sigma_model(in_use) if sig is not None else None
            if creep is not None:
                creep.observe(y, t, frozen)
            self._offsets()
        elif self.learner is not None:  # an implausible change (beyond max_force): a load, until the next rest
            self.learner.unloaded.clear = False
            self.learner.discard()
        if sig is None:
            return NO_CORRECTION
        # the tracker's covariance after this frame's predict and update; the frame's misfit
        sigma, sigma_n = sig(force, drift.P if drift is not None else None, creep_f, drift.change if drift is not None else 0.0,
                             misfit(result.consistency, in_use.consistency.expected))
        self._frame_sigma = sigma
        return Correction(corrected, sigma, sigma_n)

    def _joint_scale(self, frame: Frame, t: float | None):
        """The frame's (its ``FrameRecord``) joint measurement of the scale (force/estimators/scale_fit.py JointScale),
        None for an estimator without a joint fit (``linear``); with the controller's expected load when one is in
        effect for this frame and agrees with it (:meth:`cstomo_sensor.force.checks.expected.ExpectedLoad.for_frame`), bounded by
        the frame's own (:func:`cstomo_sensor.force.checks.expected.bounded`)."""
        self._expected_now = False
        if frame.fit is None:
            return None
        est, result = frame.in_use.estimator, frame.result
        if self._joint is None or self._joint.est is not est or self._joint_for is not self.drift:
            self._joint, self._joint_for = JointScale(est, self.drift._D[0], self.drift._D[1:]), self.drift
        e = None
        if self.expected.pending is not None and result.valid:
            e = self.expected.for_frame(t, result.force, self._frame_sigma)
        others = self.drift.others_wanted()  # counts the frame towards the other states' check
        own = self._joint.measure(None, others)
        self._expected_now = e is not None
        return own if e is None or own is None else bounded(self._joint.measure(e) or own, own)  # others: own's

    def expect_load(self, force, sigma: float, stamp_ns: int | None = None, frame_id: str | None = None,
                    source: str | None = None) -> str:
        """A controller's expected load now: ``force`` (3,) N in ``frame_id`` (None: the wrench's), its
        1-sigma ``sigma`` (N, per axis), at ``stamp_ns`` (the frames' clock; None: from the next frame),
        from the input ``source`` (its name in the log and the diagnostics; None: as before);
        checked (:meth:`cstomo_sensor.force.checks.expected.ExpectedLoad.offer`: '' accepted, else why refused), then a measurement
        of the force in the joint fit of the device's scale for frames within the tolerance of its stamp."""
        return self.expected.offer(force, sigma, stamp_ns, frame_id, source)

    def known_unloaded(self, known: bool) -> None:
        """Whether the caller knows the joint is unloaded at the next frame (a calibration recording's reference
        sensor reads no load: tools/calibrate.py, set before each frame): such a frame feeds the learner whatever the
        rest test and the step of its force say, and never discards the samples held (:class:`~.learned.Unloaded`
        guesses what a reference sensor knows), so a change whose phantom force keeps the rest test from counting
        the frames, or the tracker's settling after a load moves the force at rest, is learned from every rest."""
        self._known_rest = bool(known)

    def _learn(self, y: np.ndarray, rest: bool, force: np.ndarray | None) -> None:
        """A frame's change ``y`` into the learner (force/slow_states/learned.py) if it is clear: counted as rest (``rest``),
        or refused by the rest test with no load since the latest rest frame and none known (its ``force``,
        None for an implausible frame, :class:`~.learned.Unloaded`), or known to be unloaded (:meth:`known_unloaded`);
        the learner's decomposition a step on; a direction learned: one more state."""
        drift, learner = self.drift, self.learner
        noise = drift.force_noise  # the force's per-frame noise (None: no force map, rest frames only)
        known_rest = self._known_rest  # a reference sensor says no load (known_unloaded)
        if noise is None:
            clear = rest or known_rest
        else:
            e = self.expected.pending
            known = e is not None and float(np.dot(e[0], e[0])) > drift.rest_force ** 2
            clear = learner.unloaded.step(force, rest, noise, drift.frame_period, known) or known_rest
            if learner.unloaded.broke and not known_rest:  # its samples not yet counted may hold a load's first frames
                learner.discard()
        if clear:
            learner.add(drift, y)
        new = learner.tick(drift, drift.frame_period)
        if new is None:
            return
        row, per_scale = new
        self.directions = self.directions.plus(row, per_scale)
        # its state unknown as yet: 1-sigma the change the scale made (the next rest frames measure it)
        self.drift = self.drift.with_directions(row, [per_scale], max(abs(self.drift.change), 1e-3))
        self.learned_new = True
        log.info("learned a direction of the device's own change from %d clear frames (%.2f x the noise's largest, "
                 "its edge %.2f; restart 1-sigma %.2f x the scale's): tracked as state %d", learner.n * AVG,
                 learner.last_ratio, learner.last_edge, per_scale, self.drift.m - 1)

    def _offsets(self) -> None:
        # the resistivity gradients' states (the tracker's own block: after the contacts', before the learned)
        drift = self.drift
        if drift is not None and self._block_for is not drift:  # the tracker's blocks are fixed when it is made
            self._block, self._block_for = drift.gradients_block, drift
        self.gradient = drift.gradient[self._block].tolist() if drift is not None else None
        d = self.drift.offset if self.drift is not None else None
        c = self.creep.offset if self.creep is not None else None
        self.offset = (d if c is None else c) if c is None or d is None else np.add(d, c, out=self._sum)

    def _sigma_model(self, in_use: InUse) -> ForceSigma:
        """The force's uncertainty for the estimator and calibration (``in_use``: the pipeline's ``InUse`` of
        the frame), tracker and creep in use (rebuilt when one changes)."""
        drift, f, est, cal = self.drift, self._sigma_for, in_use.estimator, in_use.calibration
        if self._sigma is None or f[0] is not est or f[1] is not drift or f[2] is not self.creep or f[3] is not cal:
            k_rel, self.sigma_source = relative_error(cal, est.name)
            fitted = getattr(cal, "creep_per_decade", None) is not None
            creep_rel = 0.0 if self.creep is None else CREEP_REL_FITTED if fitted else CREEP_REL_ASSUMED
            self._sigma = ForceSigma(force_map(est), change_noise(est.noise, in_use.reference_frames), in_use.keep.copy(),
                                     None if drift is None else drift.state_directions, k_rel, creep_rel, est)
            self._sigma_for = (est, drift, self.creep, cal)
        return self._sigma

    def creep_text(self, calibration) -> str:
        """The creep compensated and where its coefficient comes from, for the diagnostics."""
        c = self.creep_per_decade(calibration)
        if c <= 0:
            return "not compensated (creep_per_decade 0)"
        if calibration is not None and getattr(calibration, "creep_per_decade", None) is not None:
            return f"{c:.2%} per decade, from the calibration {calibration.path}"
        return (f"{c:.2%} per decade, assumed (creep_per_decade; a rubber's is 2..6 %: fit it with "
                "cstomo calibrate from held loads, docs/calibration.md#the-creep)")

    def status(self, calibration) -> tuple[int, list[str], dict]:
        """The diagnostics' level (0 OK), problems and figures."""
        drift, level, msgs = self.drift, 0, []
        if drift is not None:
            level, d_msg = drift_status(drift)
            kv = dict(drift_change=f"{drift.change:+.3%}", drift_kelvin=kelvin_text(drift),
                      drift_rest_frames=drift.rest_frames, drift_since_rest=since_rest_text(drift))
            msgs = [d_msg] if d_msg else []
        else:
            kv = dict(drift_change="not tracked (drift_tracking false)" if not self.tracking
                      else "not tracked yet: no reference (tracking starts with the tare)")
        kv.update(creep=self.creep_text(calibration))
        if self.age_s is not None:
            kv.update(reference_age=f"{self.age_s:.0f} s: a saved tare (a restart), the states widened for it")
        e_level, e_msgs, e_kv = self.expected.status()
        kv.update(e_kv)
        return max(level if msgs else 0, e_level), msgs + e_msgs, kv


def kelvin_text(drift: DriftTracker) -> str:
    """The tracked change as a temperature change of the rubber at :data:`RESISTIVITY_PER_K`."""
    kelvin = math.log(drift.scale) / math.log1p(RESISTIVITY_PER_K) if drift.scale > 0 else math.nan
    return f"{kelvin:+.1f} K at {RESISTIVITY_PER_K:.1%}/K, or a drive drift"


def since_rest_text(drift: DriftTracker) -> str:
    """When the states were last measured at rest, and the change at the tracked rate since."""
    ago, change = drift.since_rest()
    if ago is None and not drift.rest_frames:
        return "no rest frame yet"
    ago = "" if ago is None else f"{ago:.1f} s ago, "
    return f"{ago}a change of {change:.2%} at the tracked rate since; zero 1-sigma {drift.unmeasured_n:.2f} N"


def drift_status(drift: DriftTracker) -> tuple[int, str]:
    """(0 OK, 1 WARN; a message) of the tracked change for the diagnostics."""
    c = drift.change
    text = f"{c:+.2%} since the tare (about {kelvin_text(drift)})"
    if abs(c) > VALIDATED:
        level, msg = 1, f"device changed {text}: beyond the {VALIDATED:.0%} the zero tracking is validated for; re-tare"
    elif abs(c) > RETARE_ADVISED:
        level, msg = 0, f"device changed {text}: a re-tare is advised when the joint is free"
    else:
        level, msg = 0, ""
    if drift.unmeasured_n > UNMEASURED_N:
        lost = (f"the device's gradient and contacts unmeasured since the last rest frame ({since_rest_text(drift)}): "
                "they follow its scale by their slope at rest; sigma_n says how unsure, the next rest re-acquires them")
        level, msg = 1, f"{lost}; {msg}" if msg else lost
    return level, msg
