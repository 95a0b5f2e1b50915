"""``cstomo_sensor_node``: the sensor's managed (lifecycle) ROS 2 node, publishing the joint's force.

A thin ROS adapter over the one frame loop (:mod:`cstomo_sensor.frame_path.loop`): a source of stamped frames
(the board: :class:`~cstomo_sensor.frame_path.sources.SerialSource`, read, decoded and processed by one thread;
or ``~/raw_voltages_in``: :class:`~.sources.TopicSource`, processed in its callback) through the
sensor's :class:`~cstomo_sensor.frame_path.stream.FrameStream` to the publishers
(:class:`~.sinks.Publishers`: one per output of :data:`~cstomo_sensor.frame_path.outputs.OUTPUTS`, each message
built only while someone subscribes). ``cstomo replay`` and ``cstomo estimate`` are the same loop.

configure: one frozen :class:`~.params.NodeConfig` from the parameters, the pipeline, the stream, the
input and the reference (the saved tare, else a tare on the first frames); activate: publish;
deactivate: stop; cleanup/shutdown: release. ``autostart`` (default) walks to active by itself.
Parameters: :mod:`.params`; entry point: :mod:`.startup`; logs to ``/rosout``: :mod:`.log`. docs/node.md.
"""
from __future__ import annotations

import math
import sys
import threading
import time
import traceback
from dataclasses import replace

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import WrenchStamped
from rclpy._rclpy_pybind11 import RCLError
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.task import Future
from std_msgs.msg import Empty
from std_srvs.srv import Trigger

from ..board.driver import set_os_thread_name
from ..frame_path.loop import connect, run, step
from ..frame_path.outputs import RAW_TOPIC
from ..frame_path.pipeline import Pipeline
from ..frame_path.sources import SerialSource
from ..frame_path.stream import FrameStream
from ..model.geometry import load_sensor
from . import log as ros_log
from . import status
from .params import NodeConfig
from .sinks import Publishers
from .sources import TopicSource
from .startup import as_double, build_progress, check_inputs, declare_all, failure_cause, link_warnings, refuse_unknown
from .startup import main as _main

#: Seconds of frames the driver keeps for the frame thread (at least FRAME_QUEUE frames: 4 at 100 frames/s,
#: 40 at 1000; 4 with ``rate_hz`` 0, the board's own rate); when it falls behind the oldest is dropped
#: (counted as ``dropped_overflow``): a controller wants the newest frame, not a backlog. Bounded in time,
#: not in frames, so that the frames one read brings together (a late board or a USB link deliver them in
#: bursts) are kept at any rate: at 1000 frames/s a queue of 4 frames dropped 11.6 % of them.
FRAME_QUEUE_S = 0.04
FRAME_QUEUE = 4


def frame_queue(rate_hz: float) -> int:
    """The driver's queue at ``rate_hz`` frames/s (0: the board's own rate, unknown here)."""
    return max(FRAME_QUEUE, math.ceil(FRAME_QUEUE_S * rate_hz - 1e-9))
#: The frame thread's name, for the OS too (``/proc/<pid>/task/<tid>/comm``): it reads the board,
#: decodes and processes its frames.
FRAME_THREAD = "cstomo_frames"


class CstomoSensorNode(LifecycleNode):
    """The sensor as a lifecycle node; see the module docstring and docs/node.md."""

    def __init__(self, node_name: str = "cstomo_sensor", **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        overrides = self._parameter_overrides  # rclpy's: given by files, launch, -p and the caller
        overrides.update({n: as_double(p) for n, p in overrides.items()})  # rate_hz:=200 is 200.0
        declare_all(self, overrides)
        refuse_unknown(self, overrides)
        self.add_pre_set_parameters_callback(lambda params: [as_double(p) for p in params])
        self.add_post_set_parameters_callback(self._parameters_set)
        self.config: NodeConfig | None = None
        self.pipe: Pipeline | None = None
        self.stream: FrameStream | None = None
        self.tare_path = None  # where the tare is saved and read back (set at configure)
        self._t_start = time.monotonic()
        self._active = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._source = self._pubs = None
        self._subs: list = []  # a controller's inputs: ~/joint_free, ~/expected_wrench
        self._diag_pub = self._diag_timer = self._tare_srv = self._tare_forced_srv = None
        self._tare_group, self._expected_group = MutuallyExclusiveCallbackGroup(), MutuallyExclusiveCallbackGroup()
        self._sim_time = False  # use_sim_time, for the frames' clock (_configure): asking the clock costs 25 us
        self._log_handler = ros_log.attach(self.get_logger(), self.context.ok)  # library records reach /rosout
        self.autostart_failed = Future()  # done when autostart could not configure (main exits then)
        if self.get_parameter("autostart").value:
            self._autostart_timer = self.create_timer(0.0, self._autostart)
        else:  # say that it is up, and what it waits for
            self.get_logger().info(f"autostart is false: unconfigured until told, e.g. `ros2 lifecycle set "
                                   f"{self.get_fully_qualified_name()} configure` (then activate)")

    @property
    def reference_source(self) -> str:
        """Where the reference in use comes from, in words ("none" before configure)."""
        return self.stream.tares.source if self.stream is not None else "none"

    @property
    def tare_refused(self) -> str:
        """Why the latest tare was refused ('' if none was)."""
        return self.stream.tares.refused if self.stream is not None else ""

    @property
    def active(self) -> bool:
        """The lifecycle state is active (frames are published)."""
        return self._active

    @property
    def driver(self):
        """The board's driver (serial input), else None."""
        return self._source.driver if isinstance(self._source, SerialSource) else None

    @property
    def published(self) -> dict[str, int]:
        """Messages published per topic (the diagnostics' ``messages_published``)."""
        return self._pubs.published if self._pubs is not None else {}

    @property
    def diagnostics_name(self) -> str:
        """The status name in ``/diagnostics``: the node's full name (two sensors never merge)."""
        return f"{self.get_fully_qualified_name()}: sensor"

    def _parameters_set(self, params: list[Parameter]) -> None:
        """A run-time change: ``stale_timeout`` (rclpy refuses the read-only others; ``use_sim_time`` is followed)."""
        for p in params:
            self._sim_time = p.value is True if p.name == "use_sim_time" else self._sim_time
            if p.name == "stale_timeout" and self.config is not None:
                self.config = replace(self.config, stream=replace(self.config.stream, stale_timeout=p.value))
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
            if self.context.ok():  # else SIGINT/SIGTERM while configuring: the node is ending, not failing
                self.get_logger().error(f"refusing to start: {failure_cause(err)}")
                self.get_logger().debug("".join(traceback.format_exception(err)))
            self._release()
            return TransitionCallbackReturn.FAILURE

    def _configure(self) -> TransitionCallbackReturn:
        cfg = NodeConfig.from_parameters(lambda n: self.get_parameter(n).value)
        log = self.get_logger()
        geometry = load_sensor(cfg.pipeline.sensor)  # a bad sensor file is named before anything else
        self.tare_path = check_inputs(cfg, geometry, self.get_namespace())
        t0 = time.monotonic()
        pipe = Pipeline.build(cfg.pipeline, progress=build_progress(self.context, log))
        log.info(f"model of '{cfg.pipeline.sensor}' ready in {time.monotonic() - t0:.2f} s "
                 f"({len(pipe.centers)} cells, estimator {cfg.pipeline.estimator})")
        log.info(f"calibration: {pipe.calibration.path} ({pipe.calibration.accuracy})" if pipe.calibration
                 else "calibration: none (the nominal model; `cstomo calibrate` fits one on known loads)")
        self.config, self.pipe = cfg, pipe
        self.stream = FrameStream(pipe, cfg.stream, tare_file=self.tare_path,
                                  tare_comment=f"cstomo_sensor tare of '{cfg.pipeline.sensor}' "
                                               f"(geometry {pipe.geometry.digest()})",
                                  started=self._t_start)  # the tare's log counts from the node's start
        why = self.stream.init_reference(cfg.tare_on_start)
        if why:
            elapsed = time.monotonic() - self._t_start  # a slow first model build delays the tare: say so
            (log.info if cfg.tare_on_start and elapsed < 10.0 else log.warning)(
                f"{why}: taring on the first {cfg.stream.tare_frames} frames from now, {elapsed:.0f} s after start (the "
                "joint must be unloaded); no force is published before the tare is taken")
        qos = cfg.qos()
        serial = cfg.input == "serial"
        self._pubs = Publishers(self, self.stream.outputs + ((RAW_TOPIC,) if serial else ()), pipe.centers,
                                cfg.stream.frame_id, qos, pipe.geometry, lambda: self._active, self.stream.want_fields)
        self._diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._diag_timer = self.create_timer(1.0, self._publish_diagnostics)
        self._tare_srv = self.create_service(Trigger, "~/tare", self._on_tare, callback_group=self._tare_group)
        self._subs = [self.create_subscription(Empty, "~/joint_free", self._on_joint_free, 10),
                      self.create_subscription(WrenchStamped, "~/expected_wrench", self._on_expected, 1,  # the newest counts
                                               callback_group=self._expected_group)]
        self._tare_forced_srv = self.create_service(Trigger, "~/tare_forced", self._on_tare_forced,
                                                    callback_group=self._tare_group)
        self._stop.clear()
        if serial:
            for text in link_warnings(cfg):
                log.warning(text)
            clock, self._sim_time = self.get_clock(), self.get_parameter("use_sim_time").value is True  # ROS time?
            now_ns = lambda: clock.now().nanoseconds if self._sim_time else time.time_ns()  # noqa: E731
            self._source = SerialSource(cfg.port, now_ns=now_ns, clock_window=cfg.clock_window,
                                        protocol=cfg.protocol, baudrate=cfg.baudrate, rate_hz=cfg.rate_hz or None,
                                        queue_size=frame_queue(cfg.rate_hz), stall_timeout=max(cfg.stream.stale_timeout, 0.2))
            self._thread = threading.Thread(target=self._serial_loop, name=FRAME_THREAD, daemon=True)
            self._thread.start()
        else:
            self._source = TopicSource(self, "~/raw_voltages_in", qos)
            connect(self._source, self.stream)
            stream, sinks = self.stream, [self._pubs]
            sensor = self.get_namespace()

            def handler(frame) -> None:
                with ros_log.sensor(sensor):  # the library's records of this frame name the sensor (a host)
                    step(stream, sinks, frame, self._process_now())

            self._source.handler = handler
        log.info(f"configured: input {cfg.input} ({cfg.port if serial else '~/raw_voltages_in'}), "
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

    on_shutdown = on_error = on_cleanup

    def _release(self) -> None:
        self._active = False
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._source is not None:
            self._source.close()
            self._source = None
        for sub in self._subs:
            self.destroy_subscription(sub)
        if self._pubs is not None:
            self._pubs.close()
        self._subs, self._pubs = [], None
        for destroy, what in ((self.destroy_timer, self._diag_timer), (self.destroy_publisher, self._diag_pub),
                              (self.destroy_service, self._tare_srv), (self.destroy_service, self._tare_forced_srv)):
            if what is not None:
                destroy(what)
        self._diag_pub = self._diag_timer = self._tare_srv = self._tare_forced_srv = None
        if self.stream is not None:
            self.stream.close()  # a tare still being written is saved before the node stops
        self.pipe = self.stream = None

    # --- tare --------------------------------------------------------------------------------------

    def _on_tare(self, request: Trigger.Request, response: Trigger.Response, forced: bool = False) -> Trigger.Response:
        with ros_log.sensor(self.get_namespace()):  # its records name the sensor (a host)
            return self._tare_service(request, response, forced)

    def _tare_service(self, request: Trigger.Request, response: Trigger.Response, forced: bool = False
                      ) -> Trigger.Response:
        """A tare is a transaction (:meth:`FrameStream.tare`): it ends on its own frames within the
        deadline (accepted, or refused: not steady, under load, on a ramp, the board reconnected), or
        it is cancelled; only an accepted one changes the reference and the saved file. ``forced``
        (``~/tare_forced``): the load checks do not refuse it, and the answer says what it overrode."""
        cfg, stream = self.config, self.stream
        if stream is None:
            response.success, response.message = False, "not configured"
            return response
        wait = stream.tare_deadline(cfg.rate_hz)
        outcome, taken = stream.tare(wait, forced=forced)
        response.success, response.message = status.tare_answer(self, outcome, taken, wait, forced)
        return response

    def _on_joint_free(self, _msg: Empty) -> None:
        """A controller's hint (``~/joint_free``, std_msgs/Empty): re-zero now, as a tare with its rules."""
        if self.stream is not None and not self.stream.joint_free():
            self.get_logger().info("~/joint_free: a tare is already pending")

    def _on_expected(self, msg: WrenchStamped) -> None:
        """``~/expected_wrench``: the load a controller expects now, to ``expected_wrench_sigma`` per axis;
        the stream checks it (force/checks/expected.py: a refusal is counted and said once per kind)."""
        f, h, stream = msg.wrench.force, msg.header, self.stream
        if stream is not None:  # None: released meanwhile
            stream.expect_load((f.x, f.y, f.z), self.config.expected_wrench_sigma, h.stamp.sec * 10**9 + h.stamp.nanosec,
                               h.frame_id, "~/expected_wrench")

    def _on_tare_forced(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        return self._on_tare(request, response, forced=True)  # the load checks do not refuse (docs/node.md#tare)

    def _process_now(self) -> bool:
        return self._active or self.stream.tares.pending

    def _serial_loop(self) -> None:
        set_os_thread_name(FRAME_THREAD)
        ros_log.sensor(self.get_namespace()).__enter__()  # this thread's records name the sensor (a host)
        try:  # the board's frames, read, decoded and processed on this thread (docs/node.md)
            run(self._source, self.stream, [self._pubs], stop=self._stop, process=self._process_now)
        except RCLError:
            if not self.context.ok():
                return  # ROS shut down (SIGINT) while this thread was publishing: stop quietly
            raise

    def stale_reason(self) -> str:
        """Why the data is stale ('' when fresh)."""
        return status.stale_reason(self.config, self.stream, self._source)

    def diagnostics(self) -> DiagnosticStatus:
        """The node's DiagnosticStatus now (ends the stream's period): :func:`.status.diagnostics`."""
        return status.diagnostics(self)

    def _publish_diagnostics(self) -> None:
        if self._pubs is not None:
            self._pubs.refresh()  # a subscriber the matched events missed
        arr = DiagnosticArray()
        arr.header.stamp = self.get_clock().now().to_msg()
        arr.status = [self.diagnostics()]
        self._diag_pub.publish(arr)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``cstomo_sensor_node`` (:func:`.startup.main`)."""
    return _main(CstomoSensorNode, argv)


if __name__ == "__main__":
    sys.exit(main())
