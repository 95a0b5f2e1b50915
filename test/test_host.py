"""``cstomo_sensor_host``: several sensors, one CstomoSensorNode per namespace, in one process."""
from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest
import yaml

pytest.importorskip("rclpy")

from conftest import PIPE, diagnostics_seen, wait_for  # noqa: E402

HOST = [sys.executable, "-m", "cstomo_sensor.ros.host"]
ENV = dict(os.environ, OPENBLAS_NUM_THREADS="1")


def _params_file(tmp_path, per_sensor: dict | None = None) -> str:
    common = dict(PIPE, input="topic")
    doc = {"/**": {"ros__parameters": common}}
    for name, params in (per_sensor or {}).items():
        doc[f"{name}/cstomo_sensor"] = {"ros__parameters": params}
    f = tmp_path / "sensors.yaml"
    f.write_text(yaml.safe_dump(doc))
    return str(f)


def test_namespaces_are_checked():
    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.ros.host import namespaces_of

    assert namespaces_of(["left_knee", "/right_knee/", "/arm/wrist_2"]) == ["/left_knee", "/right_knee", "/arm/wrist_2"]
    for bad in ([], ["/"], ["/a", "a"], ["/1a"], ["/a-b"]):
        with pytest.raises(ConfigError):
            namespaces_of(bad)


@pytest.mark.slow  # starts a process
def test_help_and_a_bad_namespace(capfd):
    """The installed entry point prints its help; a namespace given twice is refused (exit 2) by its main()
    in this process, before any ROS start (a second process start saved)."""
    from cstomo_sensor.ros.host import main

    r = subprocess.run(HOST + ["--help"], capture_output=True, text=True, timeout=60, env=ENV)
    assert r.returncode == 0 and r.stdout.startswith("usage: cstomo_sensor_host NAMESPACE"), r.stdout + r.stderr
    capfd.readouterr()
    assert main(["cstomo_sensor_host", "/a", "/a"]) == 2
    err = capfd.readouterr().err
    assert "given twice" in err and "Traceback" not in err, err


@pytest.mark.slow  # starts a node
def test_two_sensors_in_one_process_each_report_under_its_namespace(ros, tmp_path, warm_model):
    """Two sensors with their parameters from one file (a section each, one for both), each with its
    diagnostics named by its namespace; Ctrl-C ends the host cleanly."""
    params = _params_file(tmp_path, {f"/{n}": {"tare_file": str(tmp_path / f"{n}.csv")} for n in ("left", "right")})
    host = subprocess.Popen(HOST + ["/left", "/right", "--ros-args", "--params-file", params], env=ENV,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        with diagnostics_seen(ros) as seen:
            assert wait_for(lambda: len(seen) >= 2, 60.0), seen
    finally:
        host.send_signal(signal.SIGINT)
        err = host.stderr.read()
        code = host.wait(30)
    inputs = {name: kvs[-1].get("input", "") for name, kvs in seen.items()}
    assert inputs == {"/left/cstomo_sensor: sensor": "topic", "/right/cstomo_sensor: sensor": "topic"}, inputs
    assert code == 0 and "Traceback" not in err, err


@pytest.mark.slow  # starts a process
def test_a_refused_sensor_stops_the_host_and_is_named(tmp_path, warm_model):
    params = _params_file(tmp_path, {"/good": {"tare_file": str(tmp_path / "good.csv")},
                                     "/bad": {"sensor": str(tmp_path / "missing.yaml")}})
    r = subprocess.run(HOST + ["/good", "/bad", "--ros-args", "--params-file", params], capture_output=True,
                       text=True, timeout=90, env=ENV)
    assert r.returncode == 1, r.stderr
    assert "/bad/cstomo_sensor refused to start" in r.stderr and "missing.yaml" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr, r.stderr


def test_the_package_log_propagates_again_once_the_last_bridge_is_detached():
    """Before: detach restored propagation only when the package's logger had no handler at all; a
    handler of someone else's on it (pytest adds one to every logger that does not propagate) kept it
    off for the rest of the process, and a command's log run after a node in the same process printed
    nothing (CI: test_tools' log tests, after test_launch's node)."""
    import logging

    import rclpy.logging

    from cstomo_sensor.ros import log as ros_log

    pkg = logging.getLogger("cstomo_sensor")
    other = logging.NullHandler()  # another party's handler on the package's logger
    pkg.addHandler(other)
    try:
        first = ros_log.attach(rclpy.logging.get_logger("first"))
        second = ros_log.attach(rclpy.logging.get_logger("second"))
        assert pkg.propagate is False  # bridged: not printed a second time
        ros_log.detach(first)
        assert pkg.propagate is False  # one bridge is left
        ros_log.detach(second)
        assert pkg.propagate is True and pkg.level == logging.NOTSET
    finally:
        pkg.removeHandler(other)


def test_the_hosts_log_names_the_sensor_of_each_tare_line(capfd):
    """In one process of several sensors, a library record (the tare's lines, the frame path's) logged
    while a sensor's frames or tare service are handled names that sensor (before: 'force.reference.tare_transaction: tare
    taken ...' from /left and /right alike); a record outside any sensor has no prefix."""
    import logging

    import rclpy

    from cstomo_sensor.ros import log as ros_log
    from cstomo_sensor.ros.host import sensor_of

    handler = ros_log.attach(rclpy.logging.get_logger("cstomo_sensor_host"), label=sensor_of)
    taring = logging.getLogger("cstomo_sensor.force.reference.tare_transaction")
    try:
        with ros_log.sensor("/left"):
            taring.info("tare taken at 12.5 s")
            with ros_log.sensor("/right"):
                taring.warning("not steady; the previous reference stays")
            taring.info("tare saved")
        taring.info("outside any sensor")
    finally:
        ros_log.detach(handler)
    err = capfd.readouterr().err
    assert "]: /left: force.reference.tare_transaction: tare taken at 12.5 s" in err, err
    assert "]: /right: force.reference.tare_transaction: not steady; the previous reference stays" in err, err
    assert "]: /left: force.reference.tare_transaction: tare saved" in err, err  # back to /left after the inner block
    assert "]: force.reference.tare_transaction: outside any sensor" in err, err
