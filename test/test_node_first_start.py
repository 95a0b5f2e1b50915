"""A safe first start (issue 12 item 5): a node with no saved tare of this device publishes no force
from the model's reference frame (a real device is never the nominal one:
docs/physics.md#real-devices). It tares on its first frames, says so in the log and in /diagnostics, and only then
publishes; the forces at zero load are then near zero. Real node, real rclpy, a simulated board
(an honestly simulated device, not the model's mesh) on a virtual link (harness in conftest.py)."""
from __future__ import annotations

import numpy as np
import pytest
from conftest import BAG_RATE, diag, diag_records, start, wait_for

rclpy = pytest.importorskip("rclpy")

LOADED = 30  # a frame of the committed bag under 20 N (test/data/raw_voltages_truth.csv)


class Unloaded:
    """The committed bag's first frames (the device unloaded, honest simulation), looping."""

    def __init__(self, bag):
        self.frames = bag.frames[:20]

    def frame(self, t, rng):
        return self.frames[int(round(t * BAG_RATE)) % len(self.frames)]

    def truth(self, t):
        return np.zeros(3)


def test_first_start_without_a_saved_tare_tares_before_any_force(ros, tmp_path, source, warm_model, capfd):
    from geometry_msgs.msg import WrenchStamped

    capfd.readouterr()
    h, board = start(ros, tmp_path, Unloaded(source), rate=100.0, tare_frames=30)  # tare_on_start false
    try:
        assert h.node.reference_source == "tare pending" and h.node.pipe.reference is None
        wr = h.record("/cstomo_sensor/wrench", WrenchStamped)
        dg = diag_records(h)
        # before any frame: diagnostics say why nothing is published, at WARN
        assert wait_for(lambda: len(dg) > 0, 5.0)
        level, message, kv = diag(dg[0][1])
        assert level >= 1 and "no reference yet" in message and "unloaded" in message, message
        assert kv["reference"] == "tare pending" and kv["tare_taken"] == ""
        assert not wr
        board.start()
        assert wait_for(lambda: len(wr) > 50, 15.0)
        # the tare file is written by a thread of its own while frames flow (a busy disk took 1.2 s)
        assert wait_for(lambda: h.node.reference_source.startswith("tare saved to"), 10.0), h.node.reference_source
        assert (tmp_path / "tare.csv").is_file()
        force = np.array([[m.wrench.force.x, m.wrench.force.y, m.wrench.force.z] for _, m in wr])
        # zero load: the device's own reference gives ~0 N from the very first wrench (the model's
        # reference gave a phantom 3.5 N)
        assert np.linalg.norm(force, axis=1).max() < 1.0, np.linalg.norm(force, axis=1).max()
        assert wait_for(lambda: diag(dg[-1][1])[2]["tare_taken"] != "", 5.0)
        level, message, kv = diag(dg[-1][1])
        assert "30 frames" in kv["tare_taken"] and "after start" in kv["tare_taken"], kv
        assert "no reference yet" not in message
    finally:
        board.close()
        h.close()
    err = capfd.readouterr().err
    line = next(ln for ln in err.splitlines() if "taring on the first" in ln)
    assert "WARN" in line and "no saved tare of this device" in line and "no force is published" in line, line
    assert any("tare taken at" in ln and "INFO" in ln for ln in err.splitlines()), err


def test_a_refused_tare_at_start_is_logged_and_taken_again(ros, tmp_path, source, warm_model, capfd):
    """A joint that moves during the tare at start: the tare is refused with the reason (WARN), no
    force is published, and it is taken again on the next frames."""
    from geometry_msgs.msg import WrenchStamped

    class Moving(Unloaded):
        def frame(self, t, rng):  # a 20 N frame every other 0.2 s: never steady
            return source.frames[LOADED if int(t / 0.2) % 2 else 0]

    capfd.readouterr()
    h, board = start(ros, tmp_path, Moving(source), rate=100.0, tare_frames=30, name="moving")
    try:
        wr = h.record("/moving/wrench", WrenchStamped)
        dg = diag_records(h)
        board.start()
        assert wait_for(lambda: h.node.tare_refused != "", 10.0)
        assert wait_for(lambda: any("last tare refused" in diag(m)[1] for _, m in dg), 5.0)
        assert not wr and h.node.pipe.reference is None and h.node.processor.taring
    finally:
        board.close()
        h.close()
    err = capfd.readouterr().err
    assert any("tare refused: frames not steady" in ln and "WARN" in ln and "taring again" in ln
               for ln in err.splitlines()), err
