"""The suite's two tiers (docs/design.md#tests): a test not marked slow starts no process and no ROS
context; test/conftest.py fails one that does, naming it; a slow test may."""
import multiprocessing
import os
import subprocess
import sys

import pytest
from conftest import FastTierError


def test_a_fast_test_that_starts_a_process_fails_naming_itself():
    me = "test_tiers.py::test_a_fast_test_that_starts_a_process_fails_naming_itself"
    with pytest.raises(FastTierError, match=f"{me} is in the fast tier .* started a process"):
        subprocess.run([sys.executable, "-c", "pass"])
    with pytest.raises(FastTierError, match="started a process"):
        multiprocessing.get_context("fork").Process(target=print).start()
    assert os.fork.__wrapped__ and os.posix_spawn.__wrapped__  # guarded too (not called: a fork would run on)


def test_a_fast_test_that_starts_a_ros_context_fails():
    rclpy = pytest.importorskip("rclpy")
    ctx = rclpy.Context()
    with pytest.raises(FastTierError, match="a ROS context"):
        rclpy.init(context=ctx)
    assert not ctx.ok()


@pytest.mark.slow
def test_a_slow_test_may_start_both():
    import rclpy

    assert subprocess.run([sys.executable, "-c", "print('ran')"], capture_output=True, text=True).stdout == "ran\n"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        assert ctx.ok()
    finally:
        rclpy.try_shutdown(context=ctx)
