"""``cstomo_sensor_node``: the managed (lifecycle) ROS 2 node of the sensor.

configure: read the parameters into one frozen :class:`~.params.NodeConfig`, load (or build) the
:class:`~cstomo_sensor.force.pipeline.Pipeline`, open the input (serial board or ``~/raw_voltages_in``)
and set the reference (tare at start, else the saved tare, else the model's reference with a WARN).
activate: publish. deactivate: stop publishing. cleanup/shutdown: release port, threads, pipeline.
With ``autostart`` (default) the node walks itself to active, so ``ros2 run`` needs no manager.

Frames go through :class:`~cstomo_sensor.force.pipeline.FrameProcessor` and
:class:`~cstomo_sensor.ros.messages.OutputMessages`, shared with ``cstomo replay``. Parameters and
the config are in :mod:`.params`; the library's log records reach ``/rosout`` through :mod:`.log`.
See docs/node.md.
"""
from __future__ import annotations

import difflib
import importlib
import math
import signal
import sys
import threading
import time
import traceback
from collections import deque
from dataclasses import replace

import numpy as np
import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy._rclpy_pybind11 import RCLError
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.task import Future
from std_msgs.msg import Float32MultiArray
from std_srvs.srv import Trigger

from ..board.clock import ClockMapper
from ..board.driver import BoardDriver
from ..board.wire import DATA_WIRE_BYTES, link_frame_rate
from ..cache import check_writable
from ..errors import ConfigError, CstomoError, FrameError, NoUsableChannelsError
from ..force.device import read_reference, write_reference
from ..force.filter import LowPass
from ..force.pipeline import FrameProcessor, Pipeline, TareOutcome
from ..model.geometry import load_sensor
from . import log as ros_log
from .messages import (
    CONSISTENCY_TOPIC,
    FILTERED_TOPIC,
    FORCE_TOPICS,
    RAW_TOPIC,
    SCENE_TOPIC,
    STRESS_TOPIC,
    TOPIC_TYPES,
    OutputMessages,
    RawVoltagesCdr,
    values_from_raw_msg,
)
from .params import PARAMETERS, NodeConfig

#: Frames the driver keeps for the frame thread; when it falls behind the oldest is dropped (counted
#: as ``dropped_overflow``): a controller wants the newest frame, not a backlog, so at most this many
#: frame periods of staleness (4 ms at 1000 frames/s, 40 ms at 100).
FRAME_QUEUE = 4


class _Stats:
    """Counters of the frame path, reset per diagnostics period where noted (guarded by a lock)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.frames = 0          # frames handled (all time)
        self.period_frames = 0   # frames handled since the last diagnostics
        self.corrupt = 0         # malformed input messages (topic mode; the driver counts the board's)
        self.rejected = 0        # frames dropped by the frame path (pipeline, errors), all causes
        self.all_excluded = 0    # ... of which every measurement was excluded by the board's flags
        self.errors = 0          # ... of which an unexpected exception (a bug) was the cause
        self.reject_reason = ""  # why the latest frame was dropped; '' once a frame goes through
        self.period_reason = ""  # the latest reason this diagnostics period
        self.late = 0            # frames dropped as measured longer than stale_timeout ago (monotonic clock)
        self.proc_sum = 0.0      # per-frame processing seconds, this period
        self.proc_max = 0.0
        self.proc_n = 0
        self.residual = math.nan
        self.consistency = math.nan  # the latest frame's statistic against the socket load model
        self.foreign = 0         # frames flagged as a foreign load (all time)
        self.period_foreign = 0  # ... this period
        self.last_frame = None   # time.monotonic() of the latest frame


class CstomoSensorNode(LifecycleNode):
    """The sensor as a lifecycle node; see the module docstring and docs/node.md."""

    def __init__(self, node_name: str = "cstomo_sensor", **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        overrides = self._parameter_overrides  # rclpy's: given by files, launch, -p and the caller
        overrides.update({n: _as_double(p) for n, p in overrides.items()})  # rate_hz:=200 is 200.0
        for name, (default, desc) in PARAMETERS.items():
            self.declare_parameter(name, default, desc)
        _refuse_unknown(self, overrides)
        self.add_pre_set_parameters_callback(lambda params: [_as_double(p) for p in params])
        self.add_post_set_parameters_callback(self._parameters_set)
        self.config: NodeConfig | None = None
        self.pipe = None
        self.processor: FrameProcessor | None = None
        self.reference_source = "none"
        self.tare_taken = ""    # when the reference in use was tared (log and diagnostics)
        self.tare_refused = ""  # the latest refused tare: when and why
        self._t_start = time.monotonic()
        self.tare_path = None  # where the tare is saved and read back (set at configure)
        self._active = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._driver = None
        self._sub = None
        self._pubs: dict = {}
        self._diag_pub = self._diag_timer = self._tare_srv = None
        self._stats = _Stats()
        self._proc_lock = threading.Lock()  # one frame at a time through the processor
        self._tare_done = threading.Event()
        self._tare_outcome: tuple[TareOutcome, str] | None = None  # set by the frame thread
        self._board_clock = ClockMapper()
        self._last_diag = self._last_diag_start = time.monotonic()
        self._loss_history: deque = deque()  # (monotonic, frames, losses by kind) per diagnostics
        self._last_rejected = 0
        self._last_implausible = 0
        self._tare_group = MutuallyExclusiveCallbackGroup()
        self._log_handler = ros_log.attach(self.get_logger(), self.context.ok)  # library records reach /rosout
        self.autostart_failed = Future()  # done when autostart could not configure (main exits then)
        if self.get_parameter("autostart").value:
            self._autostart_timer = self.create_timer(0.0, self._autostart)

    def _parameters_set(self, params: list[Parameter]) -> None:
        """Apply a run-time change (rclpy refused the read-only parameters already, with the reason
        "read-only"): ``stale_timeout`` is the only one that may change while running."""
        for p in params:
            if p.name == "stale_timeout" and self.config is not None:
                self.config = replace(self.config, stale_timeout=p.value)
                self.get_logger().info(f"stale_timeout is now {p.value} s")

    def destroy_node(self) -> None:
        if hasattr(self, "_log_handler"):  # not when __init__ refused the parameters
            ros_log.detach(self._log_handler)
        super().destroy_node()

    # --- lifecycle ---------------------------------------------------------------------------------

    def _autostart(self) -> None:
        self._autostart_timer.cancel()
        self.destroy_timer(self._autostart_timer)
        if self.trigger_configure() == TransitionCallbackReturn.SUCCESS:
            self.trigger_activate()
        else:
            self.autostart_failed.set_result(True)

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        # rclpy's lifecycle swallows an exception raised here (the node just stays unconfigured and
        # main() exits 1 without a word): every failure is logged with its cause and refused here.
        try:
            return self._configure()
        except Exception as err:  # noqa: BLE001 - see above; the cause is logged, nothing is hidden
            self.get_logger().error(f"refusing to start: {failure_cause(err)}")
            self.get_logger().debug("".join(traceback.format_exception(err)))
            self._release()
            return TransitionCallbackReturn.FAILURE

    def _configure(self) -> TransitionCallbackReturn:
        cfg = NodeConfig.from_parameters(lambda n: self.get_parameter(n).value)
        log = self.get_logger()
        load_sensor(cfg.pipeline.sensor)  # a bad sensor file is named before anything else
        check_writable(cfg.cache_path)  # at once, not after a long model build

        t0 = time.monotonic()
        pipe = Pipeline.build(cfg.pipeline, progress=lambda msg: log.info(f"model: {msg}"))
        log.info(f"model of '{cfg.pipeline.sensor}' ready in {time.monotonic() - t0:.2f} s "
                 f"({len(pipe.centers)} cells, estimator {cfg.pipeline.estimator})")
        log.info(f"calibration: {pipe.calibration.path} ({pipe.calibration.accuracy})" if pipe.calibration
                 else "calibration: none (the nominal model; `cstomo calibrate` fits one on known loads)")
        self.config, self.pipe = cfg, pipe
        self.tare_path = cfg.tare_path_for(pipe.geometry)
        self._board_clock = ClockMapper(cfg.clock_window)
        self._stats = _Stats()
        self._loss_history.clear()
        self._last_diag_start = time.monotonic()
        self._last_rejected = 0
        self.processor = FrameProcessor(pipe, stress_field_every=cfg.stress_field_every, on_tare=self._tare_ended)
        self.out = OutputMessages(pipe.centers, cfg.frame_id)
        self._raw_cdr = RawVoltagesCdr()
        self._filter = LowPass(cfg.wrench_filter_hz, max_gap=cfg.stale_timeout)  # restarts after a gap
        self._reconnects = 0
        self._init_reference()
        qos = cfg.qos()
        topics = list(FORCE_TOPICS) + [STRESS_TOPIC, CONSISTENCY_TOPIC] \
            + ([SCENE_TOPIC] if pipe.scene_field is not None else []) \
            + ([RAW_TOPIC] if cfg.input == "serial" else []) + ([FILTERED_TOPIC] if cfg.wrench_filter_hz > 0 else [])
        for topic in topics:
            self._pubs[topic] = self.create_lifecycle_publisher(_msg_class(TOPIC_TYPES[topic]), f"~/{topic}", qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._diag_timer = self.create_timer(1.0, self._publish_diagnostics)
        self._tare_srv = self.create_service(Trigger, "~/tare", self._on_tare, callback_group=self._tare_group)
        self._stop.clear()
        if cfg.input == "serial":
            if cfg.protocol == "text":
                log.warning("protocol 'text' has no checksum: a corrupted line that still parses is taken as "
                            "a frame (only the plausibility gate guards it); use 'binary' (CRC-32) if the board can")
            carried = link_frame_rate(cfg.baudrate)
            if cfg.protocol == "binary" and cfg.rate_hz > carried:
                log.warning(f"rate_hz {cfg.rate_hz:g} exceeds what baudrate {cfg.baudrate} carries: at most "
                            f"{carried:.0f} DATA frames/s of {DATA_WIRE_BYTES} bytes (8N1), so a UART link lags and "
                            f"loses frames; use baudrate >= {cfg.rate_hz * 10 * DATA_WIRE_BYTES:.0f} or a USB CDC "
                            "board (which ignores the baud rate: then this warning does not apply); docs/protocol.md")
            self._driver = BoardDriver(cfg.port, protocol=cfg.protocol, baudrate=cfg.baudrate,
                                       rate_hz=cfg.rate_hz or None, queue_size=FRAME_QUEUE,
                                       stall_timeout=max(cfg.stale_timeout, 0.2))
            self._thread = threading.Thread(target=self._serial_loop, name="cstomo_frames", daemon=True)
            self._thread.start()
        else:
            self._sub = self.create_subscription(Float32MultiArray, "~/raw_voltages_in", self._on_raw, qos)
        log.info(f"configured: input {cfg.input} ({cfg.port if cfg.input == 'serial' else '~/raw_voltages_in'}), "
                 f"reference: {self.reference_source}")
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = True
        return super().on_activate(state)

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._active = False
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        self._release()
        return TransitionCallbackReturn.SUCCESS

    def _release(self) -> None:
        self._active = False
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._driver is not None:
            self._driver.close()
            self._driver = None
        if self._sub is not None:
            self.destroy_subscription(self._sub)
            self._sub = None
        for pub in self._pubs.values():
            self.destroy_lifecycle_publisher(pub)
        self._pubs = {}
        if self._diag_timer is not None:
            self.destroy_timer(self._diag_timer)
        if self._diag_pub is not None:
            self.destroy_publisher(self._diag_pub)
        if self._tare_srv is not None:
            self.destroy_service(self._tare_srv)
        self._diag_pub = self._diag_timer = self._tare_srv = None
        self.pipe = self.processor = None

    # --- reference (tare) --------------------------------------------------------------------------

    def _init_reference(self) -> None:
        """The saved tare of this device if usable, else a tare on the first frames (``tare_on_start``
        always tares): no force is ever computed against the model's own reference frame, which is
        not the device's (a phantom force of several newtons at zero load)."""
        cfg, log, path = self.config, self.get_logger(), self.tare_path
        self.tare_taken = self.tare_refused = ""
        why = "tare_on_start is true"
        if not cfg.tare_on_start:
            why = f"no saved tare of this device at {path}"
            if path.is_file():
                try:
                    ref, noise, n_ref = read_reference(path, self.pipe.n_meas)
                    why = tare_problem(ref, self.pipe.model_reference)
                    if not why:
                        report = self.pipe.set_reference(ref, noise, n_ref)
                        self.reference_source = f"saved tare {path}"
                        log.info(f"saved tare {path}: mean of {n_ref} frame(s), noise "
                                 f"{'measured' if noise is not None else 'assumed 60 dB'}")
                        (log.warning if report.warn else log.info)(f"tare: {report.message}")
                        return
                    why = f"saved tare {path} not used: {why}"
                except (CstomoError, OSError) as err:
                    why = f"saved tare {path} unusable ({err})"
        self.processor.start_tare(cfg.tare_frames)
        self.reference_source = "tare pending"
        elapsed = time.monotonic() - self._t_start  # a slow first model build delays the tare: say so
        (log.info if cfg.tare_on_start and elapsed < 10.0 else log.warning)(
            f"{why}: taring on the first {cfg.tare_frames} frames from now, {elapsed:.0f} s after start (the joint "
            "must be unloaded); no force is published before the tare is taken")

    def _save_tare(self, outcome: TareOutcome) -> str:
        """Write an accepted tare to ``tare_path`` and its noise beside it (``.noise.csv``, atomically);
        returns '' or why it was not saved."""
        cfg, path = self.config, self.tare_path
        self.reference_source = "tare"
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            write_reference(path, outcome.reference, outcome.noise,
                            comment=f"cstomo_sensor tare of '{cfg.pipeline.sensor}' "
                                    f"(geometry {self.pipe.geometry.digest()}): mean of "
                                    f"{outcome.frames} frames, {time.strftime('%Y-%m-%dT%H:%M:%S%z')}",
                            frames=outcome.frames)
        except OSError as err:
            note = f"tare in use but not saved to {path} ({err}): fix tare_file and tare again"
            self.get_logger().error(note)
            return note
        self.reference_source = f"tare saved to {path}"
        self.get_logger().info(f"tare saved to {path}")
        return ""

    def _tare_ended(self, outcome: TareOutcome) -> None:
        """The processor ended a tare (frame thread, under ``_proc_lock``): save it if accepted and
        hand the outcome to a waiting ``~/tare`` call."""
        log, when = self.get_logger(), time.strftime("%H:%M:%S")
        if outcome.ok:
            self.tare_taken = f"{when}, {time.monotonic() - self._t_start:.1f} s after start, " \
                              f"{outcome.frames} frames, spread {outcome.spread:.2%}"
            log.info(f"tare taken at {self.tare_taken}")
            note = self._save_tare(outcome)
            self._filter.reset()  # a new reference: the filtered wrench starts again from the next frame
        else:
            self.tare_refused = f"{when}: {outcome.reason}"
            log.warning(f"{outcome.reason}" + (" (no reference yet: taring again on the next frames)"
                                               if self.processor.taring else ""))
            note = ""
        self._tare_outcome = (outcome, note)
        self._tare_done.set()

    def _on_tare(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """A tare is a transaction: it ends on its own frames within the deadline (accepted, or
        refused as not steady), or it is cancelled; only an accepted one changes the reference and
        the saved file."""
        cfg, proc = self.config, self.processor
        if proc is None:
            response.success, response.message = False, "not configured"
            return response
        n = cfg.tare_frames
        wait = cfg.stale_timeout + n * 0.1 + 2.0
        with self._proc_lock:
            self._tare_done.clear()
            self._tare_outcome = None
            proc.start_tare(n)
        self._tare_done.wait(wait)
        with self._proc_lock:  # decided under the lock: a tare cannot end while it is cancelled
            ended, self._tare_outcome = self._tare_outcome, None
            taken = proc.cancel_tare() if ended is None else n
        unchanged = f"the reference ({self.reference_source}) and {self.tare_path} are unchanged"
        if ended is None:
            why = self.stale_reason() or "frames late, dropped or rejected"
            msg = f"tare cancelled: {taken} of {n} frames within {wait:.1f} s ({why}); {unchanged}; call ~/tare " \
                  "again once frames arrive"
            if proc.taring:
                msg += " (the tare at start stays pending: no reference yet)"
            self.get_logger().warning(msg)
            response.success, response.message = False, msg
            return response
        outcome, note = ended
        if not outcome.ok:
            response.success, response.message = False, f"{outcome.reason}, then call ~/tare again; {unchanged}"
            return response
        response.success = True
        response.message = f"reference from {n} frames (spread {outcome.spread:.2%} of its rms); " \
                           f"{note or self.reference_source}"
        return response

    # --- frames ------------------------------------------------------------------------------------

    def _serial_loop(self) -> None:
        drv = self._driver
        while not self._stop.is_set():
            try:
                frame = drv.get(0.1)
                if frame is None:
                    continue
                # the board clock is mapped onto the host's monotonic clock (it cannot step), which
                # gives the frame's age; the stamp is the ROS time now minus that age
                now_ns = self.get_clock().now().nanoseconds
                age_ns = 0  # text mode: no board clock
                reconnects = drv.stats().reconnects
                if reconnects != self._reconnects:  # the board came back: the filtered wrench starts again
                    self._reconnects = reconnects
                    self._filter.reset()
                if frame.board_time_us is not None:
                    mono_ns = time.monotonic_ns()
                    age_ns = mono_ns - self._board_clock.stamp_ns(frame.board_time_us, mono_ns)
                self._handle(frame.values, frame.saturated, frame.contact_ok, now_ns - age_ns, age_ns, raw=True)
            except RCLError as err:
                if not self.context.ok():
                    return  # ROS shut down (SIGINT) while this thread was publishing: stop quietly
                self._frame_dropped(err)
            except Exception as err:  # noqa: BLE001 - the frame boundary: counted, logged, reported
                self._frame_dropped(err)

    def _on_raw(self, msg: Float32MultiArray) -> None:
        host_ns = self.get_clock().now().nanoseconds
        try:
            values = values_from_raw_msg(msg)
        except FrameError as err:
            with self._stats.lock:
                self._stats.corrupt += 1
            self.get_logger().warning(f"dropped input frame: {err}", throttle_duration_sec=5.0)
            return
        try:
            self._handle(values, None, None, host_ns, 0, raw=False)
        except Exception as err:  # noqa: BLE001 - the frame boundary, as in _serial_loop
            self._frame_dropped(err)

    def _frame_dropped(self, err: Exception) -> None:
        """Count, log (throttled) and report a frame the frame path dropped; the caller goes on."""
        bug = not isinstance(err, FrameError)
        reason = f"{type(err).__name__}: {err}" if bug else str(err)
        st = self._stats
        with st.lock:
            st.rejected += 1
            st.all_excluded += isinstance(err, NoUsableChannelsError)
            st.errors += bug
            st.reject_reason = st.period_reason = reason
        if bug:
            self.get_logger().error("frame dropped on an unexpected error (a bug: please report it with this "
                                    f"trace):\n{''.join(traceback.format_exception(err))}",
                                    throttle_duration_sec=5.0)
        else:
            self.get_logger().warning(f"dropped frame: {reason}", throttle_duration_sec=5.0)

    def _handle(self, values, saturated, contact_ok, stamp_ns: int, age_ns: int, raw: bool) -> None:
        """One frame measured ``age_ns`` ago (monotonic): count it, drop it if older than
        ``stale_timeout``, maybe publish raw, process (tare or result), publish outputs.

        Raises whatever the frame path raises; the callers count it (:meth:`_frame_dropped`)."""
        t0 = time.perf_counter()
        st, proc, cfg = self._stats, self.processor, self.config
        with st.lock:
            st.frames += 1
            st.period_frames += 1
            st.last_frame = time.monotonic()
        if proc is None:
            return
        if age_ns > cfg.stale_timeout * 1e9:
            with st.lock:
                st.late += 1
            return
        active = self._active
        if raw and active:
            self._pubs[RAW_TOPIC].publish(self._raw_cdr(values))  # CDR bytes (messages.py)
        if not (active or proc.taring):
            return
        with self._proc_lock:
            result = proc.process(values, saturated, contact_ok)
        if st.reject_reason:
            with st.lock:
                st.reject_reason = ""  # frames go through again
        if result is None or not result.valid or not self._active:
            return  # an implausible frame is no force: counted by the processor, shown in diagnostics
        pubs = self._pubs
        for topic, data in self.out.build(result, stamp_ns).items():
            pubs[topic].publish(data)  # CDR bytes, serialised by OutputMessages
        if cfg.wrench_filter_hz > 0:
            pubs[FILTERED_TOPIC].publish(self.out.wrench(self._filter(result.force, stamp_ns * 1e-9), stamp_ns))
        dt = time.perf_counter() - t0
        with st.lock:
            st.proc_sum += dt
            st.proc_n += 1
            st.proc_max = max(st.proc_max, dt)
            if not math.isnan(result.residual):
                st.residual = result.residual
            st.consistency = result.consistency
            if result.foreign_load:
                st.foreign += 1
                st.period_foreign += 1

    # --- diagnostics -------------------------------------------------------------------------------

    def stale_reason(self) -> str:
        """Why the data is stale ('' when fresh)."""
        cfg, st = self.config, self._stats
        if cfg is None:
            return "not configured"
        last = st.last_frame
        age = math.inf if last is None else time.monotonic() - last
        if age <= cfg.stale_timeout:
            return ""
        what = "no frames yet" if last is None else f"no frames for {age:.1f} s (stale_timeout {cfg.stale_timeout} s)"
        if self._driver is not None:
            ds = self._driver.stats()
            if not ds.connected:
                what += f"; board disconnected ({ds.last_error or 'port not open'})"
            elif ds.last_error:
                what += f"; last error: {ds.last_error}"
        elif self._sub is not None and self.count_publishers(self._sub.topic_name) == 0:
            what += f"; nobody publishes {self._sub.topic_name}"
        return what

    def diagnostics(self) -> DiagnosticStatus:
        """The node's DiagnosticStatus now (resets the per-period figures)."""
        cfg, st = self.config, self._stats
        now = time.monotonic()
        period, self._last_diag = max(now - self._last_diag, 1e-9), now
        with st.lock:
            rate = st.period_frames / period
            proc_mean = st.proc_sum / st.proc_n if st.proc_n else math.nan
            proc_max = st.proc_max if st.proc_n else math.nan
            st.period_frames, st.proc_sum, st.proc_max, st.proc_n = 0, 0.0, 0.0, 0
            corrupt, late, residual, frames = st.corrupt, st.late, st.residual, st.frames
            rejected, period_reason, st.period_reason = st.rejected, st.period_reason, ""
            consistency, foreign, period_foreign, st.period_foreign = st.consistency, st.foreign, st.period_foreign, 0
            kv_rejected = {"frames_rejected": rejected, "frames_all_excluded": st.all_excluded,
                           "frame_errors": st.errors, "reject_reason": st.reject_reason}
        status = DiagnosticStatus(name=f"{self.get_name()}: sensor", hardware_id=cfg.port if cfg and cfg.input == "serial" else "")
        kv = {"state": "active" if self._active else "inactive", "input": cfg.input if cfg else "",
              "reference": self.reference_source, "frames": frames, "frame_rate_hz": f"{rate:.1f}",
              "late_dropped": late}
        level, msgs = DiagnosticStatus.OK, []
        ds = self._driver.stats() if self._driver is not None else None
        losses = {"corrupt": corrupt, "late": late}
        if ds is not None:
            kv.update(connected=ds.connected, dropped_overflow=ds.dropped_overflow, reconnects=ds.reconnects,
                      seq_gaps=ds.seq_gaps, duplicates=ds.duplicates, reordered=ds.reordered, resyncs=ds.resyncs,
                      frame_period_ms=f"{ds.period * 1e3:.1f}", last_error=ds.last_error)
            losses.update(corrupt=corrupt + ds.corrupt, gaps=ds.seq_gaps, duplicates=ds.duplicates,
                          reordered=ds.reordered, overflow=ds.dropped_overflow)
            if not ds.connected:
                level, msgs = DiagnosticStatus.ERROR, msgs + ["board disconnected"]
        kv["corrupt"] = losses["corrupt"]
        loss_level, loss_msg = self._loss_level(now, frames, losses)
        if loss_msg:
            level = max(level, loss_level)
            msgs.append(loss_msg)
        kv.update(kv_rejected)
        if rejected > self._last_rejected:
            level = max(level, DiagnosticStatus.WARN)
            msgs.append(f"{rejected - self._last_rejected} frames rejected ({period_reason})")
        self._last_rejected = rejected
        ex = self.processor.excluded if self.processor is not None else None
        if ex is not None:
            kv.update(saturated_channels=ex.saturated, dead_electrodes=",".join(str(e + 1) for e in ex.dead_electrodes),
                      excluded_channels=ex.channels)
            if ex.channels:
                level = max(level, DiagnosticStatus.WARN)
                msgs.append(f"{ex.channels} channels excluded (saturated {ex.saturated}, dead electrodes "
                            f"{[e + 1 for e in ex.dead_electrodes]})")
        proc = self.processor
        imp = proc.implausible if proc is not None else 0
        new_imp = imp - self._last_implausible if imp >= self._last_implausible else imp
        self._last_implausible = imp
        kv.update(implausible=imp, implausible_reason=proc.implausible_reason if proc is not None else "",
                  checksum=("crc32" if cfg.protocol == "binary" else "none (text mode)") if cfg and cfg.input == "serial" else "n/a")
        if new_imp:
            level = max(level, DiagnosticStatus.WARN)
            msgs.append(f"{new_imp} implausible frames not published ({proc.implausible_reason})")
        kv.update(consistency=f"{consistency:.4g}", foreign_load_frames=foreign)
        if period_foreign:
            level = max(level, DiagnosticStatus.WARN)
            threshold = self.pipe.consistency.threshold if self.pipe is not None else math.nan
            msgs.append(f"foreign load: {period_foreign} frames not explained by a load on the socket (consistency "
                        f"{consistency:.3g}, limit {threshold:g}); something else presses the sensor or an "
                        "electrode changed; forces still published")
        kv.update(residual=f"{residual:.4g}", processing_time_mean_ms=f"{proc_mean * 1e3:.3f}",
                  processing_time_max_ms=f"{proc_max * 1e3:.3f}")
        reason = self.stale_reason() if self._active else ""
        kv["stale_reason"] = reason
        if reason:
            level = DiagnosticStatus.ERROR if ds is not None and not ds.connected else max(level, DiagnosticStatus.WARN)
            msgs.insert(0, f"stale: {reason}")
        kv.update(tare_taken=self.tare_taken, tare_refused=self.tare_refused)
        if proc is not None and proc.taring and self.pipe is not None and self.pipe.reference is None:
            level = max(level, DiagnosticStatus.WARN)
            msgs.append("no reference yet: taring on the first frames (the joint must be unloaded); no force "
                        "published until then" + (f"; last tare refused at {self.tare_refused}" if self.tare_refused else ""))
        pipe = self.pipe
        report = pipe.scale_report if pipe is not None else None
        if report is not None:
            kv.update(reference_scale=f"{report.factor:.4g}", reference_unexplained=f"{report.unexplained:.4f}",
                      noise="measured by the tare" if pipe.noise_measured else "assumed 60 dB")
            if report.warn:
                level = max(level, DiagnosticStatus.WARN)
                msgs.append(report.message)
        if pipe is not None:
            cal = pipe.calibration
            kv.update(calibration=cal.path if cal else "none (nominal model)",
                      calibration_accuracy=cal.accuracy if cal else "")
        status.level = level
        status.message = "; ".join(msgs) or ("streaming" if self._active else "inactive")
        status.values = [KeyValue(key=k, value=str(v)) for k, v in kv.items()]
        return status

    def _loss_level(self, now: float, frames: int, losses: dict) -> tuple[int, str]:
        """The level and message of the frames lost or dropped over the last :data:`LOSS_WINDOW` s
        (``losses``: running totals by kind); WARN above :data:`LOSS_WARN`, ERROR above
        :data:`LOSS_ERROR` of the frames the board sent meanwhile."""
        hist = self._loss_history
        if not hist:
            hist.append((self._last_diag_start, 0, {}))
        hist.append((now, frames, dict(losses)))
        while len(hist) > 2 and now - hist[1][0] >= LOSS_WINDOW:
            hist.popleft()
        t0, f0, old = hist[0]
        d = {k: v - old.get(k, 0) for k, v in losses.items()}
        lost = sum(d.values())
        sent = frames - f0 + lost - d["late"]  # late frames were received (and counted in frames)
        if lost <= 0 or sent <= 0 or lost <= LOSS_WARN * sent:
            return DiagnosticStatus.OK, ""
        level = DiagnosticStatus.ERROR if lost > LOSS_ERROR * sent else DiagnosticStatus.WARN
        parts = ", ".join(f"{k} {v}" for k, v in d.items() if v)
        return level, f"{lost} of {sent} frames lost or dropped in the last {now - t0:.0f} s ({parts})"

    def _publish_diagnostics(self) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self.diagnostics()]
        self._diag_pub.publish(arr)


#: Seconds over which lost and dropped frames (corrupt, sequence gaps, late, duplicated, reordered,
#: queue overflow) are judged, and the fractions of the frames sent in that time above which the
#: status is WARN and ERROR.
LOSS_WINDOW = 5.0
LOSS_WARN = 0.01
LOSS_ERROR = 0.2

#: A saved tare whose rms lies outside these multiples of the model reference's rms is not a frame of
#: this sensor: voltages scale with the rubber's resistivity, 0.2..5 times nominal (REFERENCE_SENSOR.md s.8).
TARE_RMS_RATIO = (0.2, 5.0)


def tare_problem(ref: np.ndarray, model_reference: np.ndarray) -> str:
    """Why the saved tare ``ref`` (n_meas,) is implausible for a model whose reference is
    ``model_reference``; '' if it is plausible."""
    if not np.all(np.isfinite(ref)):
        return "it holds non-finite values"
    if not np.any(ref):
        return "all its values are zero"
    ratio = float(np.sqrt(np.mean(ref**2)) / np.sqrt(np.mean(model_reference**2)))
    lo, hi = TARE_RMS_RATIO
    if not lo <= ratio <= hi:
        return (f"its rms is {ratio:.3g} times the model reference's, outside {lo:g}..{hi:g} (a rubber "
                "within REFERENCE_SENSOR.md section 8); a tare of another sensor or board?")
    return ""


def failure_cause(err: BaseException) -> str:
    """One line naming what failed at configure and what to do."""
    if isinstance(err, CstomoError):
        return str(err)
    if isinstance(err, ImportError):
        from ..errors import install_hint

        return (f"missing optional dependency '{err.name or err}' ({err}): {install_hint(err.name)}; "
                "or choose settings that do not need it")
    if isinstance(err, OSError):
        where = f"{err.filename}: " if err.filename else ""
        return f"{where}{err.strerror or err} ({type(err).__name__}): check the file or device and its permissions"
    return f"{type(err).__name__}: {err} (unexpected: please report it with the debug log)"


#: Parameters rclpy declares later (QoS overrides of publishers): not unknown to the node.
_RCLPY_PREFIXES = ("qos_overrides.",)


def _as_double(p: Parameter) -> Parameter:
    """An integer given for a parameter whose default is a float, as that float (``rate_hz:=200``)."""
    default = PARAMETERS.get(p.name, (None,))[0]
    if isinstance(default, float) and p.type_ == Parameter.Type.INTEGER:
        return Parameter(p.name, Parameter.Type.DOUBLE, float(p.value))
    return p


def _refuse_unknown(node: LifecycleNode, overrides: dict) -> None:
    """A parameter given to the node (file, launch, -p) that it does not have is a mistake
    (``tare_on_star``): refused with the nearest known name."""
    unknown = sorted(n for n in overrides if n not in PARAMETERS and not n.startswith(_RCLPY_PREFIXES)
                     and not node.has_parameter(n))
    if unknown:
        hints = []
        for n in unknown:
            near = difflib.get_close_matches(n, list(PARAMETERS), n=1)
            hints.append(f"'{n}'" + (f" (did you mean '{near[0]}'?)" if near else ""))
        raise ConfigError(f"unknown parameter{'s' if len(hints) > 1 else ''} {', '.join(hints)}: expected names "
                          f"from config/cstomo_sensor.yaml ({', '.join(PARAMETERS)})")


def _msg_class(type_name: str):
    pkg, _, name = type_name.split("/")

    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def usage() -> str:
    """``cstomo_sensor_node --help``: how to run it and every parameter with its default."""
    lines = ["usage: cstomo_sensor_node [-h] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] [-r __ns:=/NS]]",
             "", __doc__.splitlines()[0].replace("``", ""), "",
             "Publishes ~/wrench, ~/force_magnitude, ~/force_elevation, ~/force_azimuth, ~/stress_field, "
             "~/raw_voltages, /diagnostics; service ~/tare (docs/node.md).", "", "parameters (default):"]
    for name, (default, desc) in PARAMETERS.items():
        lines.append(f"  {name:<20} {default!r:<16} {desc.description}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cstomo_sensor_node`` (``ros2 run cstomo_sensor cstomo_sensor_node``)."""
    argv = list(argv if argv is not None else sys.argv)
    own = argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]
    if "-h" in own or "--help" in own:
        print(usage())
        return 0
    rclpy.init(args=argv)
    try:
        node = CstomoSensorNode()
    except (InvalidParameterTypeException, InvalidParameterValueException, ConfigError) as err:  # overrides refused
        print(f"cstomo_sensor_node: {err}", file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    executor = MultiThreadedExecutor(num_threads=2)
    executor.add_node(node)
    code = 0
    try:
        executor.spin_until_future_complete(node.autostart_failed)
        if node.autostart_failed.done():
            code = 1  # configure refused (the log says why); the parameters are read-only: restart needed
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        # a second Ctrl-C (or the one rclpy's handler passes on just after shutting the context
        # down) must not interrupt the joins below with a KeyboardInterrupt traceback
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        node._release()
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
