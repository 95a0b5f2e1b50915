"""The serial link's own limit (docs/protocol.md section 1.9): the DATA frame's size on the wire, the
rate a baud rate carries, and the node's warning at start when the requested rate exceeds it."""
from __future__ import annotations

import numpy as np
import pytest

from cstomo_sensor.board.wire import BITS_PER_BYTE, DATA_WIRE_BYTES, DataFrame, encode, link_frame_rate


def test_data_frames_on_the_wire_are_at_most_data_wire_bytes():
    rng = np.random.default_rng(0)
    sizes = [len(encode(DataFrame(seq=int(rng.integers(2**32)), board_time_us=int(rng.integers(2**50)),
                                  values=rng.normal(size=208) * 0.1))) for _ in range(300)]
    # 1 + 4 + 872 + 4 packet bytes... 0x00 + COBS(880 bytes) + 0x00: 883 (zeros inside) to 886 (none)
    assert max(sizes) <= DATA_WIRE_BYTES == 886 and min(sizes) >= 883
    assert BITS_PER_BYTE == 10  # 8N1
    assert link_frame_rate(921600) == pytest.approx(921600 / 8860)
    assert 104 < link_frame_rate(921600) < 105 and link_frame_rate(12_000_000) > 1000 > link_frame_rate(8_000_000)


@pytest.mark.slow  # starts a node
@pytest.mark.parametrize("rate, baud, warned", [(1000.0, 921600, True), (100.0, 921600, False),
                                                 (1000.0, 12_000_000, False)])
def test_the_node_warns_when_the_rate_exceeds_the_baud_rate(ros, capfd, tmp_path, warm_model, rate, baud, warned):
    pytest.importorskip("rclpy")
    from conftest import PIPE, Harness

    capfd.readouterr()
    h = Harness(ros, dict(PIPE, port=str(tmp_path / "nothing"), rate_hz=rate, baudrate=baud, autostart=False),
                name=f"link_{int(rate)}_{baud}")
    try:
        h.node.trigger_configure()
    finally:
        h.close()
    err = capfd.readouterr().err
    assert ("exceeds what baudrate" in err) == warned, err
    if warned:
        assert f"rate_hz {rate:g} exceeds what baudrate {baud} carries: at most 104 DATA frames/s" in err
