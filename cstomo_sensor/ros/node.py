"""``cstomo_sensor_node``: the sensor's managed (lifecycle) ROS 2 node, publishing the joint's force.

A thin ROS adapter over the sensor's :class:`~cstomo_sensor.force.stream.FrameStream`.

configure: read the parameters into one frozen :class:`~.params.NodeConfig`, load (or build) the
:class:`~cstomo_sensor.force.pipeline.Pipeline`, make the frame stream (reference, tare, masks,
filter, counts), open the input (serial board or ``~/raw_voltages_in``) and set the reference (the
saved tare, else a tare on the first frames). activate: publish. deactivate: stop publishing.
cleanup/shutdown: release port, threads, stream. With ``autostart`` (default) the node walks itself
to active, so ``ros2 run`` needs no manager.

The node keeps the lifecycle, the parameters, the publishers (one per output of the stream:
:data:`~cstomo_sensor.force.stream.OUTPUTS`) and the formatting of its diagnostics; what happens to a
frame is the stream's, shared with ``cstomo replay`` and ``cstomo estimate``. Parameters and the
config are in :mod:`.params`; the library's log records reach ``/rosout`` through :mod:`.log`.
See docs/node.md.
"""
from __future__ import annotations

import difflib
import importlib
import math
import os
import signal
import sys
import threading
import time
import traceback
from dataclasses import replace

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import WrenchStamped
from rclpy._rclpy_pybind11 import RCLError
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.task import Future
from sensor_msgs.msg import Image
from std_msgs.msg import Empty
from std_srvs.srv import Trigger

from ..board.clock import ClockMapper
from ..board.driver import BoardDriver, check_port, set_os_thread_name
from ..board.links import holds, is_virtual
from ..board.wire import DATA_WIRE_BYTES, link_frame_rate
from ..cache import check_writable
from ..errors import ConfigError, CstomoError, FrameError
from ..force.pipeline import Pipeline
from ..force.stream import ERROR, OK, OUTPUTS, WARN, FrameStream
from ..model.geometry import load_sensor
from . import log as ros_log
from .messages import RAW_TOPIC, TOPIC_TYPES, OutputMessages, RawVoltagesCdr, frame_from_raw_msg
from .params import PARAMETERS, NodeConfig

#: Frames the driver keeps for the frame thread; when it falls behind the oldest is dropped (counted
#: as ``dropped_overflow``): a controller wants the newest frame, not a backlog, so at most this many
#: frame periods of staleness (4 ms at 1000 frames/s, 40 ms at 100).
FRAME_QUEUE = 4
#: The frame thread's name, for the OS too (``/proc/<pid>/task/<tid>/comm``; the driver's reader
#: thread is :data:`~cstomo_sensor.board.driver.READER_THREAD`).
FRAME_THREAD = "cstomo_frames"


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
        self.pipe: Pipeline | None = None
        self.stream: FrameStream | None = None
        self.tare_path = None  # where the tare is saved and read back (set at configure)
        self._t_start = time.monotonic()
        self._active = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._driver = None
        self._sub = self._free_sub = None
        self._pubs: dict = {}
        self._published: dict[str, int] = {}  # messages published per topic since configure (diagnostics)
        self._diag_pub = self._diag_timer = self._tare_srv = self._tare_forced_srv = None
        self._tare_group = MutuallyExclusiveCallbackGroup()
        self._log_handler = ros_log.attach(self.get_logger(), self.context.ok)  # library records reach /rosout
        self.autostart_failed = Future()  # done when autostart could not configure (main exits then)
        if self.get_parameter("autostart").value:
            self._autostart_timer = self.create_timer(0.0, self._autostart)

    @property
    def processor(self) -> FrameStream | None:
        """The frame stream (the name the tests and tools knew it by)."""
        return self.stream

    @property
    def reference_source(self) -> str:
        return self.stream.reference_source if self.stream is not None else "none"

    @property
    def tare_refused(self) -> str:
        return self.stream.tare_refused if self.stream is not None else ""

    @property
    def diagnostics_name(self) -> str:
        """The status name in ``/diagnostics``: the node's full name, namespace included, so two
        sensors never merge in an aggregator."""
        return f"{self.get_fully_qualified_name()}: sensor"

    def _parameters_set(self, params: list[Parameter]) -> None:
        """Apply a run-time change (rclpy refused the read-only parameters already, with the reason
        "read-only"): ``stale_timeout`` is the only one that may change while running."""
        for p in params:
            if p.name == "stale_timeout" and self.config is not None:
                self.config = replace(self.config, stale_timeout=p.value)
                if self.stream is not None:
                    self.stream.with_config(stale_timeout=p.value)
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
        geometry = load_sensor(cfg.pipeline.sensor)  # a bad sensor file is named before anything else
        if cfg.input == "serial":
            check_port(cfg.port)  # a file or a directory is no board: said once, not retried for ever
            if is_virtual(cfg.port) and not holds(cfg.port):  # nothing outside this process can make one
                raise ConfigError(f"port {cfg.port!r}: no simulated board of this process holds it (virtual:// "
                                  "serves a board made in the node's own process: tests, benchmarks); expected "
                                  "a serial device")
        check_writable(cfg.cache_path)  # at once, not after a long model build
        # the tare must be saved: a node that cannot would re-tare under any load at every restart
        self.tare_path = cfg.tare_path_for(geometry, self.get_namespace())
        check_writable(self.tare_path.parent, f"the tare file {self.tare_path}: its directory",
                       "set the parameter 'tare_file' to a path in a writable directory")
        if self.tare_path.is_dir():
            raise ConfigError(f"parameter 'tare_file'={str(self.tare_path)!r}: a directory; expected a file path")

        t0 = time.monotonic()
        pipe = Pipeline.build(cfg.pipeline, progress=lambda msg: log.info(f"model: {msg}"))
        log.info(f"model of '{cfg.pipeline.sensor}' ready in {time.monotonic() - t0:.2f} s "
                 f"({len(pipe.centers)} cells, estimator {cfg.pipeline.estimator})")
        log.info(f"calibration: {pipe.calibration.path} ({pipe.calibration.accuracy})" if pipe.calibration
                 else "calibration: none (the nominal model; `cstomo calibrate` fits one on known loads)")
        self.config, self.pipe = cfg, pipe
        self.stream = FrameStream(pipe, cfg.stream, tare_file=self.tare_path,
                                  tare_comment=f"cstomo_sensor tare of '{cfg.pipeline.sensor}' "
                                               f"(geometry {pipe.geometry.digest()})",
                                  started=self._t_start)  # the tare's log counts from the node's start
        self._board_clock = ClockMapper(cfg.clock_window)
        self.out = OutputMessages(pipe.centers, cfg.frame_id)
        self._raw_cdr = RawVoltagesCdr(cfg.frame_id)
        self._reconnects = 0
        why = self.stream.init_reference(cfg.tare_on_start)
        if why:
            elapsed = time.monotonic() - self._t_start  # a slow first model build delays the tare: say so
            (log.info if cfg.tare_on_start and elapsed < 10.0 else log.warning)(
                f"{why}: taring on the first {cfg.tare_frames} frames from now, {elapsed:.0f} s after start (the "
                "joint must be unloaded); no force is published before the tare is taken")
        qos = cfg.qos()
        self._published = {}
        topics = self.stream.outputs + ((RAW_TOPIC,) if cfg.input == "serial" else ())
        for topic in topics:
            self._pubs[topic] = self.create_lifecycle_publisher(_msg_class(TOPIC_TYPES[topic]), f"~/{topic}", qos)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._diag_timer = self.create_timer(1.0, self._publish_diagnostics)
        self._tare_srv = self.create_service(Trigger, "~/tare", self._on_tare, callback_group=self._tare_group)
        self._free_sub = self.create_subscription(Empty, "~/joint_free", self._on_joint_free, 10)
        # issue 26 item 4: a controller's expected load, a measurement of the device's states (docs/node.md)
        self._expected_sub = self.create_subscription(WrenchStamped, "~/expected_wrench", self._on_expected, 10)
        self._tare_forced_srv = self.create_service(Trigger, "~/tare_forced", self._on_tare_forced,
                                                    callback_group=self._tare_group)
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
            self._thread = threading.Thread(target=self._serial_loop, name=FRAME_THREAD, daemon=True)
            self._thread.start()
        else:
            self._sub = self.create_subscription(Image, "~/raw_voltages_in", self._on_raw, qos)
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
        for sub in (self._sub, self._free_sub):
            if sub is not None:
                self.destroy_subscription(sub)
        self._sub = self._free_sub = None
        for pub in self._pubs.values():
            self.destroy_lifecycle_publisher(pub)
        self._pubs = {}
        if self._diag_timer is not None:
            self.destroy_timer(self._diag_timer)
        if self._diag_pub is not None:
            self.destroy_publisher(self._diag_pub)
        for srv in (self._tare_srv, self._tare_forced_srv):
            if srv is not None:
                self.destroy_service(srv)
        self._diag_pub = self._diag_timer = self._tare_srv = self._tare_forced_srv = None
        if self.stream is not None:
            self.stream.close()  # a tare still being written is saved before the node stops
        self.pipe = self.stream = None

    # --- tare --------------------------------------------------------------------------------------

    def _on_tare(self, request: Trigger.Request, response: Trigger.Response, forced: bool = False) -> Trigger.Response:
        """A tare is a transaction (:meth:`FrameStream.tare`): it ends on its own frames within the
        deadline (accepted, or refused: not steady, under load, on a ramp, the board reconnected), or
        it is cancelled; only an accepted one changes the reference and the saved file. ``forced``
        (``~/tare_forced``): the load checks do not refuse it, and the answer says what it overrode."""
        cfg, stream = self.config, self.stream
        if stream is None:
            response.success, response.message = False, "not configured"
            return response
        n = cfg.tare_frames
        wait = stream.tare_deadline(cfg.rate_hz)
        outcome, taken = stream.tare(wait, forced=forced)
        unchanged = f"the reference ({self.reference_source}) and {self.tare_path} are unchanged"
        name = "~/tare_forced" if forced else "~/tare"
        if outcome is None:
            why = self.stale_reason() or "frames late, dropped or rejected"
            msg = f"tare cancelled: {taken} of {n} frames within {wait:.1f} s ({why}); {unchanged}; call {name} " \
                  "again once frames arrive"
            if stream.taring:
                msg += " (the tare at start stays pending: no reference yet)"
            self.get_logger().warning(msg)
            response.success, response.message = False, msg
        elif not outcome.ok:
            msg = f"{outcome.reason}, then call {name} again; {unchanged}"
            if outcome.check is not None and outcome.check.problems():
                msg += ("; if the joint is unloaded and the change is the device's own (warmed unevenly, contacts "
                        "changed), ~/tare_forced takes it")
            response.success, response.message = False, msg
        else:
            check = outcome.check.summary() if outcome.check is not None else "no load check"
            forced_note = ""
            if outcome.forced:
                forced_note = f"forced tare, overrode: {outcome.overridden}; " if outcome.overridden else \
                              "forced tare (the load checks passed anyway); "
            response.success = True
            response.message = f"{forced_note}reference from {n} frames (spread {outcome.spread:.2%} of its rms; " \
                               f"{check}); {outcome.note or self.reference_source}"
        return response

    def _on_joint_free(self, _msg: Empty) -> None:
        """A controller's hint (``~/joint_free``, std_msgs/Empty): re-zero now, as a tare with its rules."""
        if self.stream is not None and not self.stream.joint_free():
            self.get_logger().info("~/joint_free: a tare is already pending")

    def _on_expected(self, msg: WrenchStamped) -> None:
        """``~/expected_wrench``: the load a controller expects now, to ``expected_wrench_sigma`` per axis."""
        f, st = msg.wrench.force, msg.header.stamp
        if self.stream is not None and self.config is not None:
            try:
                self.stream.expect_load((f.x, f.y, f.z), self.config.expected_wrench_sigma, st.sec * 10**9 + st.nanosec)
            except ConfigError as err:
                self.get_logger().warning(f"~/expected_wrench ignored: {err}")

    def _on_tare_forced(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """``~/tare_forced``: :meth:`_on_tare` whose load checks do not refuse (docs/node.md#tare)."""
        return self._on_tare(request, response, forced=True)

    # --- frames ------------------------------------------------------------------------------------

    def _serial_loop(self) -> None:
        set_os_thread_name(FRAME_THREAD)
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
                if reconnects != self._reconnects:  # the board came back: the filter restarts, a pending tare ends
                    self._reconnects = reconnects
                    self.stream.reconnected()
                if frame.board_time_us is not None:
                    mono_ns = time.monotonic_ns()
                    age_ns = mono_ns - self._board_clock.stamp_ns(frame.board_time_us, mono_ns)
                stamp_ns = now_ns - age_ns
                if self._active:  # the raw frame as measured, NaN where the board flagged a measurement
                    flagged = self.stream.flagged(frame.saturated, frame.contact_ok)
                    self._pubs[RAW_TOPIC].publish(self._raw_cdr(frame.values, stamp_ns, flagged))
                    self._published[RAW_TOPIC] = self._published.get(RAW_TOPIC, 0) + 1
                self._publish(self.stream.push(frame.values, frame.saturated, frame.contact_ok, stamp_ns,
                                               age_ns, process=self._active or self.stream.taring))
            except RCLError:
                if not self.context.ok():
                    return  # ROS shut down (SIGINT) while this thread was publishing: stop quietly
                raise

    def _on_raw(self, msg: Image) -> None:
        """A recorded or relayed raw frame: stamped with its own header stamp (the time it was
        measured, as the serial node stamps it), else the host time on reception."""
        host_ns = self.get_clock().now().nanoseconds
        try:
            values, flagged, stamp_ns = frame_from_raw_msg(msg)
        except FrameError as err:
            self.stream.drop(err, corrupt=True)
            return
        self._publish(self.stream.push(values, flagged, None, stamp_ns or host_ns, 0,
                                       process=self._active or self.stream.taring))

    def _publish(self, output) -> None:
        if output is None or not output.result.valid or not self._active:
            return  # an implausible frame is no force: counted by the stream, shown in diagnostics
        pubs, counts = self._pubs, self._published
        for topic, data in self.out.build(output.result, output.stamp_ns, output.filtered).items():
            pubs[topic].publish(data)  # CDR bytes, serialised by OutputMessages
            counts[topic] = counts.get(topic, 0) + 1

    # --- diagnostics -------------------------------------------------------------------------------

    def stale_reason(self) -> str:
        """Why the data is stale ('' when fresh)."""
        cfg = self.config
        if cfg is None or self.stream is None:
            return "not configured"
        last = self.stream.counts.last_frame
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
        """The node's DiagnosticStatus now (resets the per-period figures): the stream's health, the
        board's link and the staleness."""
        cfg, stream = self.config, self.stream
        serial = cfg is not None and cfg.input == "serial"
        status = DiagnosticStatus(name=self.diagnostics_name, hardware_id=cfg.port if serial else "")
        kv = {"state": "active" if self._active else "inactive", "input": cfg.input if cfg else "",
              "reference": self.reference_source}
        level, msgs = OK, []
        ds = self._driver.stats() if self._driver is not None else None
        board = None
        if ds is not None:
            kv.update(connected=ds.connected, dropped_overflow=ds.dropped_overflow, reconnects=ds.reconnects,
                      seq_gaps=ds.seq_gaps, duplicates=ds.duplicates, reordered=ds.reordered, resyncs=ds.resyncs,
                      frame_period_ms=f"{ds.period * 1e3:.1f}", last_error=ds.last_error)
            board = dict(corrupt=ds.corrupt, gaps=ds.seq_gaps, duplicates=ds.duplicates, reordered=ds.reordered,
                         overflow=ds.dropped_overflow)
            if not ds.connected:
                level, msgs = ERROR, ["board disconnected"]
        if stream is not None:
            s_level, s_msgs, s_kv = stream.health(time.monotonic(), board)
            level, msgs = max(level, s_level), msgs + s_msgs
            kv.update(s_kv)
        kv["checksum"] = ("crc32" if cfg.protocol == "binary" else "none (text mode)") if serial else "n/a"
        reason = self.stale_reason() if self._active else ""
        kv["stale_reason"] = reason
        kv["messages_published"] = " ".join(f"{t}={n}" for t, n in sorted(dict(self._published).items()))
        if reason:
            level = ERROR if ds is not None and not ds.connected else max(level, WARN)
            msgs = [f"stale: {reason}"] + [m for m in msgs if m != "board disconnected"]  # the reason says it
        status.level = bytes([level])  # diagnostic_msgs' levels are bytes
        status.message = "; ".join(msgs) or ("streaming" if self._active else "inactive")
        status.values = [KeyValue(key=k, value=str(v)) for k, v in kv.items()]
        return status

    def _publish_diagnostics(self) -> None:
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self.diagnostics()]
        self._diag_pub.publish(arr)


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
    """``cstomo_sensor_node --help``: how to run it, what it publishes and every parameter with its default."""
    lines = ["usage: cstomo_sensor_node [-h] [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] [-r __ns:=/NS]]",
             "", __doc__.splitlines()[0].replace("``", ""), "", "publishes (in the node's namespace):"]
    lines += [f"  ~/{name:<19} {desc}" for name, desc in OUTPUTS.items()]
    lines += [f"  ~/{RAW_TOPIC:<19} sensor_msgs/Image (32FC1, 1 x 208): the board's volts, stamped when measured "
              "(serial input; NaN where the board flagged a measurement), for ros2 bag record",
              f"  {'/diagnostics':<21} diagnostic_msgs/DiagnosticArray, status named '<namespace>/<node>: sensor'",
              "services:", f"  {'~/tare':<21} std_srvs/Trigger: a new reference on the next tare_frames frames "
              "(refused under load)", f"  {'~/tare_forced':<21} std_srvs/Trigger: the same, taken even when it looks "
              "loaded (the answer says what it overrode)",
              "subscribes:", f"  {'~/joint_free':<21} std_msgs/Empty: a controller's hint that the joint is free "
              "now: re-zero at once (a tare with its rules, refused under load)",
              f"  {'~/expected_wrench':<21} geometry_msgs/WrenchStamped: the load a controller expects now (to "
              "expected_wrench_sigma), a measurement of the device's change under load",
              f"  {'~/raw_voltages_in':<21} sensor_msgs/Image, as ~/raw_voltages (input: topic)",
              "(docs/node.md)", "", "parameters (default):"]
    for name, (default, desc) in PARAMETERS.items():
        lines.append(f"  {name:<20} {default!r:<16} {desc.description}")
    return "\n".join(lines)


def own_args(argv: list[str] | None) -> tuple[list[str], list[str]]:
    """(the whole command line, the arguments before ``--ros-args``) of an entry point."""
    argv = list(argv if argv is not None else sys.argv)
    return argv, argv[1:argv.index("--ros-args")] if "--ros-args" in argv else argv[1:]


#: The parameter file of an install, as a shell finds it from any directory.
INSTALLED_CONFIG = "$(ros2 pkg prefix cstomo_sensor)/share/cstomo_sensor/config/cstomo_sensor.yaml"


def init_ros(prog: str, argv: list[str]) -> bool:
    """``rclpy.init`` on an entry point's command line; False, having said why in one line on stderr
    (no traceback), when it cannot: a ``--params-file`` that cannot be read (checked first, as rcl's
    own error names neither the directory nor the installed file), or arguments rcl refuses."""
    ros = argv[argv.index("--ros-args"):] if "--ros-args" in argv else []
    for flag, path in zip(ros, ros[1:]):
        if flag == "--params-file" and not (os.path.isfile(path) and os.access(path, os.R_OK)):
            where = "" if os.path.isabs(path) else f" in {os.getcwd()}"
            print(f"{prog}: --params-file {path}: no such readable file{where} (the installed one: "
                  f"{INSTALLED_CONFIG})", file=sys.stderr)
            return False
    try:
        rclpy.init(args=argv)
    except RCLError as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return False
    return True


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cstomo_sensor_node`` (``ros2 run cstomo_sensor cstomo_sensor_node``)."""
    argv, own = own_args(argv)
    if "-h" in own or "--help" in own:
        print(usage())
        return 0
    if not init_ros("cstomo_sensor_node", argv):
        return 2
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
