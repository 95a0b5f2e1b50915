"""Proven on a colcon install (issue 12 item 7): the package is built with colcon into a temporary
workspace, the workspace's ``install/setup.sh`` is sourced, and everything below runs from that
install, not from this checkout: the installed ``board-sim`` and node until a wrench arrives, the
launch file's simulated board command, and ``cstomo demo``. colcon-core, colcon-ros and ament_package
come from the package index (the ``test`` extra); launch/launch_ros do not, so the launch file itself
is not run here (test_launch.py tests the plan it hands to launch). The docs' robot commands run here
as written, from the workspace root, through a stand-in of ``ros2 run`` / ``ros2 pkg prefix``."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("colcon_core", reason="colcon-core is in the test extra: pip install '.[test]'")
pytest.importorskip("ament_package", reason="ros-kilted-ament-package is in the test extra")
pytest.importorskip("colcon_ros", reason="colcon-ros is in the test extra")
rclpy = pytest.importorskip("rclpy")

pytestmark = pytest.mark.slow  # a colcon build and the installed node, board and demo (~15 s)

ROOT = Path(__file__).resolve().parent.parent
SKIP = shutil.ignore_patterns(".git", ".venv", ".cache", "build", "install", "log", "out", "__pycache__",
                              "*.egg-info", ".pytest_cache", ".ruff_cache")


@pytest.fixture(scope="module")
def install(tmp_path_factory):
    """(install prefix of the workspace, environment after sourcing its setup.sh)."""
    ws = tmp_path_factory.mktemp("colcon_ws")
    shutil.copytree(ROOT, ws / "src" / "cstomo_sensor", ignore=SKIP, symlinks=True)
    colcon = [sys.executable, "-c", "import sys; from colcon_core.command import main; sys.exit(main())"]
    r = subprocess.run([*colcon, "build", "--base-paths", "src"], cwd=ws, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    prefix = ws / "install" / "cstomo_sensor"
    for f in ("share/ament_index/resource_index/packages/cstomo_sensor", "share/cstomo_sensor/package.xml",
              "share/cstomo_sensor/launch/cstomo_sensor.launch.py", "share/cstomo_sensor/config/cstomo_sensor.yaml",
              "share/cstomo_sensor/config/sensors/cuboid_joint.yaml", "share/cstomo_sensor/config/cstomo_sensor.rviz",
              "share/cstomo_sensor/config/sensors_example.yaml", "lib/cstomo_sensor/cstomo",
              "lib/cstomo_sensor/cstomo_sensor_node"):
        assert (prefix / f).is_file(), f
    # source it as a robot engineer does, and take the environment it leaves
    r = subprocess.run(["sh", "-c", f". '{ws / 'install' / 'setup.sh'}' && env -0"], capture_output=True, timeout=60,
                       env=dict(os.environ))
    assert r.returncode == 0, r.stderr
    env = dict(kv.split("=", 1) for kv in r.stdout.decode().split("\0") if "=" in kv)
    assert str(prefix) in env.get("AMENT_PREFIX_PATH", ""), env.get("AMENT_PREFIX_PATH")
    env["OPENBLAS_NUM_THREADS"] = "1"
    # the installed package is the one imported, not this checkout
    r = subprocess.run([sys.executable, "-c", "import cstomo_sensor; print(cstomo_sensor.__file__)"],
                       env=env, capture_output=True, text=True, timeout=60, cwd=ws)
    assert r.stdout.strip().startswith(str(prefix)), r.stdout + r.stderr
    return prefix, env


def test_installed_board_sim_and_node_deliver_a_wrench(install, tmp_path):
    from conftest import prepare_board
    from geometry_msgs.msg import WrenchStamped

    prefix, env = install
    lib = prefix / "lib" / "cstomo_sensor"
    from cstomo_sensor.tools.launching import SIM_LOAD

    script = tmp_path / "load.csv"
    # a launch's own script (unloaded for 3 s: the node tares), as a launch's board plays it: its frames are
    # those of the launch tests and test_board_pty's (one computation in the suite's cache, 15-40 s cold),
    # computed in this process (conftest.prepare_board) when no test before did, not in the installed board's
    # process (a factorisation of its own): the installed board reads them from the cache (the same key from
    # the installed code). The installed code computing a board's frames: test_demo_runs_from_the_install.
    script.write_text(SIM_LOAD)
    link = tmp_path / "board"
    board_cmd = [str(lib / "cstomo"), "board-sim", "--sensor", "cuboid_joint", "--rate", "100",
                 "--load-script", str(script), "--link", str(link)]
    prepare_board(board_cmd)
    node = subprocess.Popen([str(lib / "cstomo_sensor_node"), "--ros-args", "-r", "__ns:=/installed",
                             "-p", f"port:={link}", "-p", f"tare_file:={tmp_path / 'tare.csv'}"],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    board = subprocess.Popen(board_cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    probe = rclpy.create_node("colcon_probe", context=ctx)
    got = []
    probe.create_subscription(WrenchStamped, "/installed/cstomo_sensor/wrench", got.append, 10)
    try:
        from rclpy.executors import SingleThreadedExecutor

        ex = SingleThreadedExecutor(context=ctx)
        ex.add_node(probe)
        deadline = time.monotonic() + 240  # a cold cache builds the model first
        while not got and time.monotonic() < deadline and node.poll() is None:
            ex.spin_once(timeout_sec=0.2)
        assert got, "no wrench from the installed node"
        assert got[0].header.frame_id == "cstomo_socket"
    finally:
        probe.destroy_node()
        rclpy.try_shutdown(context=ctx)
        for p in (node, board):
            p.send_signal(2)
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
    out = node.stdout.read()
    assert node.returncode == 0 and "Traceback" not in out, out


def test_launch_plan_of_the_install_starts_the_installed_board(install):
    prefix, env = install
    code = ("from cstomo_sensor.tools.launching import launch_plan; import shutil; "
            "plan = launch_plan({'sim': 'true', 'config': sys.argv[1]}); print(plan.sensors[0].board[0]); "
            "shutil.rmtree(plan.work)")
    r = subprocess.run([sys.executable, "-c", "import sys; " + code,
                        str(prefix / "share" / "cstomo_sensor" / "config" / "cstomo_sensor.yaml")],
                       env=env, capture_output=True, text=True, timeout=60, cwd="/")
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == str(prefix / "lib" / "cstomo_sensor" / "cstomo"), r.stdout


def test_demo_runs_from_the_install(install, tmp_path):
    """``cstomo demo`` on a short script, run to its end, from the install: the suite's one such run
    (test_tools.py's demo is interrupted by Ctrl-C): judged by test_tools.check_demo_run, and its
    temporary files removed."""
    from test_tools import DEMO_SCRIPT, check_demo_run

    prefix, env = install
    script = tmp_path / "load.csv"
    script.write_text(DEMO_SCRIPT)
    r = subprocess.run([str(prefix / "lib" / "cstomo_sensor" / "cstomo"), "demo", "--load-script", str(script),
                        "--hold", "2.5", "--rate", "100"], env=dict(env, TMPDIR=str(tmp_path)),
                       capture_output=True, text=True, timeout=300, cwd=tmp_path)
    check_demo_run(r.returncode, r.stdout, r.stderr)
    assert not list(tmp_path.glob("cstomo_demo_*"))


def test_every_installed_scene_finds_what_it_names(install):
    from test_packaging import scene_references

    prefix, _ = install
    scenes = sorted((prefix / "share" / "cstomo_sensor" / "scenes").rglob("*.yaml"))
    assert (prefix / "share/cstomo_sensor/scenes/devices/cuboid_joint_device_a.yaml") in scenes
    for scene in scenes:
        for ref in scene_references(scene):
            assert (scene.parent / ref).is_file(), f"{scene} names {ref}: not installed"


#: A stand-in of ros2cli for ``ros2 run PKG EXE ...`` and ``ros2 pkg prefix PKG`` (ros2cli is not on the
#: package index): the package's prefix is the first AMENT_PREFIX_PATH entry holding it, as ros2cli finds it.
ROS2 = """#!/bin/sh
prefix() { (IFS=:; for p in $AMENT_PREFIX_PATH; do
  [ -f "$p/share/ament_index/resource_index/packages/$1" ] && { echo "$p"; exit 0; }; done; exit 1); }
if [ "$1 $2" = "pkg prefix" ]; then prefix "$3"; exit $?; fi
if [ "$1" = run ]; then p=$(prefix "$2") || exit 1; exe="$p/lib/$2/$3"; shift 3; exec "$exe" "$@"; fi
echo "ros2 stand-in: $*: not supported" >&2; exit 2
"""


def test_the_docs_robot_commands_work_in_the_install_as_written(install, tmp_path):
    prefix, env = install
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "ros2").write_text(ROS2)
    (bin_dir / "ros2").chmod(0o755)
    env = dict(env, PATH=f"{bin_dir}{os.pathsep}{env.get('PATH', '')}", ROS_DOMAIN_ID=env.get("ROS_DOMAIN_ID", "77"),
               ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    env.pop("ROS_DISTRO", None)
    ws = prefix.parent.parent  # the workspace root: no config/ here

    def sh(command: str, timeout: float = 60) -> subprocess.CompletedProcess:
        return subprocess.run(["sh", "-c", command], cwd=ws, env=env, capture_output=True, text=True, timeout=timeout)

    assert sh("ros2 pkg prefix cstomo_sensor").stdout.strip() == str(prefix)
    # README, Commands on a robot: both ways to run cstomo
    r = sh('export PATH="$(ros2 pkg prefix cstomo_sensor)/lib/cstomo_sensor:$PATH"\ncstomo calibrate --help')
    assert r.returncode == 0 and r.stdout.startswith("usage: cstomo calibrate"), r.stdout + r.stderr
    r = sh("ros2 run cstomo_sensor cstomo calibrate --help")
    assert r.returncode == 0 and "--bag" in r.stdout, r.stdout + r.stderr
    r = sh("ros2 run cstomo_sensor cstomo_sensor_node --help")
    assert r.returncode == 0 and r.stdout.splitlines()[2].endswith("."), r.stdout
    # a parameter file by a path that is not there: one line, no traceback
    r = sh("ros2 run cstomo_sensor cstomo_sensor_node --ros-args --params-file config/cstomo_sensor.yaml")
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.startswith("cstomo_sensor_node: --params-file config/cstomo_sensor.yaml: no such readable file")
    # the installed one, as docs/node.md gives it: the node starts on it (no board: autostart off)
    node = subprocess.Popen(["sh", "-c", "exec ros2 run cstomo_sensor cstomo_sensor_node --ros-args --params-file "
                             "$(ros2 pkg prefix cstomo_sensor)/share/cstomo_sensor/config/cstomo_sensor.yaml "
                             "-p port:=/dev/cstomo -p autostart:=false"], cwd=ws, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    up = node.stdout.readline()  # its first line says it is up and waits for a transition (no fixed sleep: a
    assert "autostart is false" in up, up + node.communicate(timeout=20)[0]  # busy host loads rclpy for seconds)
    node.send_signal(2)
    out = node.communicate(timeout=20)[0]
    assert node.returncode == 0 and "Traceback" not in out, out
    # the launch's sensors:=config/... finds the installed example; a launch needing what is not
    # installed (tf2_ros here) is refused naming it
    code = ("import sys; from cstomo_sensor.tools.launching import launch_plan; from cstomo_sensor.errors import "
            "ConfigError\ntry:\n    launch_plan({'sensors': 'config/sensors_example.yaml'}, check=True)\n"
            "except ConfigError as err:\n    print(err)")
    r = subprocess.run([sys.executable, "-c", code], cwd=ws, env=env, capture_output=True, text=True, timeout=60)
    assert r.stdout.strip() == ("parent_frame needs static_transform_publisher (package 'tf2_ros': sudo apt install "
                                "ros-$ROS_DISTRO-tf2-ros), not found"), r.stdout + r.stderr
