"""The installed console scripts end quietly on a Ctrl-C they do not handle themselves: one line and
exit status 130, no traceback (``cstomo_sensor/scripts.py``). A fresh-clone CI on a busy machine sent a
node its SIGINT while it still imported scipy, and it died with a 40-line traceback."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

BIN = Path(sys.executable).parent


def interrupted(argv: list[str], after_s: float, tmp_path: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               ROS_DOMAIN_ID=os.environ.get("ROS_DOMAIN_ID", "83"))
    # SIGINT at its default, as a terminal's shell starts a command (a background job of a script, as CI may run
    # the suite, inherits it ignored, and Python then never raises KeyboardInterrupt)
    proc = subprocess.Popen(argv, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    time.sleep(after_s)
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=30)
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


@pytest.mark.slow  # starts processes
@pytest.mark.parametrize("argv, after_s", [
    # while it still loads rclpy, numpy and scipy (1.5 s or more here)
    (["cstomo_sensor_node", "--ros-args", "-p", "autostart:=false"], 0.4),
    # in the middle of a long command (loading or running its first model: either way unhandled)
    (["cstomo", "bench", "--heldout", "60", "--out", "out"], 3.0),
])
def test_a_ctrl_c_the_command_does_not_handle_ends_it_in_one_line(argv, after_s, tmp_path):
    r = interrupted([str(BIN / argv[0]), *argv[1:]], after_s, tmp_path)
    assert r.returncode == 130, (r.returncode, r.stderr)
    assert r.stderr.endswith(f"\n{argv[0]}: stopped by Ctrl-C\n") or r.stderr == f"{argv[0]}: stopped by Ctrl-C\n", r.stderr
    assert "Traceback" not in r.stderr, r.stderr
