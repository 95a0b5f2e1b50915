"""The Cortex-M4F image (firmware/stm32): cross-built with arm-none-eabi-gcc + picolibc, it fits a
64 kB flash / 16 kB RAM part, and booted in QEMU (netduinoplus2: an STM32F405, its USART1 on a
pseudo-terminal) the real BoardDriver reads it: identity, frames in order with zero sequence gaps at
100 frames/s, the values of the frames table in the image. Skipped, naming the Debian packages, where
the cross tools or QEMU are missing."""
from __future__ import annotations

import re
import subprocess
import sys
import time

import numpy as np
import pytest
from firmware_harness import FIRMWARE, Process, build_stm32, elf_size, qemu_argv, write_frames

from cstomo_sensor.board.driver import BoardDriver
from cstomo_sensor.board.wire import Identity

FLASH, RAM = 64 * 1024, 16 * 1024
pytestmark = pytest.mark.alone  # QEMU's board in real time: no neighbour (setup.cfg)


@pytest.fixture(scope="module")
def image(tmp_path_factory):
    """The emulated board's image (the table front-end and its own frames table), cross-built once for the
    tests below that check or boot it as it is."""
    return build_stm32(tmp_path_factory.mktemp("stm32"))


@pytest.mark.slow  # runs the cross-compiler
@pytest.mark.parametrize("table", [True, False], ids=["emulated", "hardware"])
def test_the_image_fits_a_64k_flash_16k_ram_part(tmp_path, table, image):
    elf = image if table else build_stm32(tmp_path, table=False)
    text, data, bss = elf_size(elf)  # the linker script is 64k/16k as well
    assert text + data <= FLASH and data + bss <= RAM, (text, data, bss)
    assert bss >= 2048  # the stack is reserved in RAM


@pytest.mark.slow
def test_qemu_runs_the_image_and_the_driver_reads_it(tmp_path):
    rows = np.random.default_rng(4).normal(0.0, 0.1, (3, 208))
    path = write_frames(tmp_path / "frames.csv", rows)
    rows = np.loadtxt(path, delimiter=",")
    subprocess.run([sys.executable, str(FIRMWARE / "tools" / "frames_to_c.py"), str(path), str(tmp_path / "t.c"),
                    "--rows", "3"], check=True)
    elf = build_stm32(tmp_path, tmp_path / "t.c")
    debug = tmp_path / "usart2.txt"
    with Process(qemu_argv(elf, debug), device_pattern=r"redirected to (/dev/pts/\d+)") as qemu:
        driver = BoardDriver(qemu.device, rate_hz=100.0, queue_size=1 << 14)
        try:
            deadline = time.monotonic() + 30
            while driver.identity is None and time.monotonic() < deadline:
                time.sleep(0.05)
            frames, end = [], time.monotonic() + 4.0
            while time.monotonic() < end:
                f = driver.get(0.05)
                if f is not None:
                    frames.append(f)
            st = driver.stats()
        finally:
            driver.close()
    assert driver.identity == Identity("cstomo-fw 1.0 (stm32f4, table front-end)", 16, 1, 208)
    # 100 frames/s when QEMU gets a core (its UART model writes each byte to the pty with a system call);
    # a loaded host slows the emulated board, which then skips slots (not measured: no seq gap)
    assert len(frames) >= 100, (len(frames), st)
    seqs = [f.seq for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and (st.seq_gaps, st.corrupt) == (0, 0), st
    t = np.array([f.board_time_us for f in frames], float) * 1e-6
    assert 0.0099 <= (t[-1] - t[0]) / (seqs[-1] - seqs[0]) <= 0.04  # the board's clock: never faster than asked
    # each measured frame plays the table's next row; after a restart (a reopen's START) the rows go
    # on where they were, so match the first frame's row and follow
    k = next(k for k in range(3) if np.array_equal(frames[0].values, np.float32(rows[k])))
    for f in frames:
        np.testing.assert_array_equal(f.values, np.float32(rows[(k + f.seq - seqs[0]) % 3]))
    report = debug.read_text()
    assert re.search(r"measured \d+ sent \d+ no_room 0", report), report


def _lower_envelope_rate(host: np.ndarray, board: np.ndarray, window: float = 2.0) -> float:
    """The board clock's rate against the host's: between the frames of least delay (host arrival minus
    board time at its least) in the first and in the last ``window`` seconds, so that QEMU's and the
    pty's bursts (a frame late by a descheduled emulator) do not count."""
    offset = host - board
    first = np.flatnonzero(host <= host[0] + window)
    last = np.flatnonzero(host >= host[-1] - window)
    i, j = first[np.argmin(offset[first])], last[np.argmin(offset[last])]
    return float((board[j] - board[i]) / (host[j] - host[i]))


@pytest.mark.slow
def test_the_emulated_boards_clock_keeps_host_time(tmp_path, image):
    """The frames' board time advances with the host's clock within 1 % over 10 s. (The SysTick count
    the image used before lost the ticks QEMU could not deliver while its vCPU thread ran the busy
    firmware: 0.82 x host time on a loaded host, and the node's clock mapping then stamped the
    frames ever older, too stale to publish.)"""
    elf = image
    with Process(qemu_argv(elf, tmp_path / "usart2.txt"), device_pattern=r"redirected to (/dev/pts/\d+)") as qemu:
        driver = BoardDriver(qemu.device, rate_hz=100.0, queue_size=1 << 14)
        try:
            deadline = time.monotonic() + 30
            while driver.identity is None and time.monotonic() < deadline:
                time.sleep(0.05)
            host, board, end = [], [], time.monotonic() + 10.0
            while time.monotonic() < end:
                f = driver.get(0.05)
                if f is not None:
                    host.append(time.monotonic())
                    board.append(f.board_time_us * 1e-6)
            st = driver.stats()
        finally:
            driver.close()
    assert len(host) >= 200 and (st.seq_gaps, st.corrupt) == (0, 0), (len(host), st)
    host, board = np.array(host), np.array(board)
    assert host[-1] - host[0] >= 9.0
    rate = _lower_envelope_rate(host, board)
    assert abs(rate - 1.0) < 0.01, f"the board's clock runs {rate:.4f} x host time"


@pytest.mark.slow
def test_the_node_publishes_the_emulated_boards_frames(ros, tmp_path, warm_model, image):
    """The real node, its port on QEMU's pty, tares on the image's first frames and publishes a wrench
    for (nearly) every frame the driver delivers over 10 s: none stamped too old to publish (the
    stream drops frames older than stale_timeout by the board's clock mapped to the host's)."""
    from conftest import PIPE, Harness, wait_for
    from geometry_msgs.msg import WrenchStamped

    elf = image
    with Process(qemu_argv(elf, tmp_path / "usart2.txt"), device_pattern=r"redirected to (/dev/pts/\d+)") as qemu:
        p = dict(PIPE, port=qemu.device, tare_file=str(tmp_path / "tare.csv"), tare_on_start=True, tare_frames=4,
                 rate_hz=100.0)
        h = Harness(ros, p, name="cstomo_qemu")
        try:
            assert wait_for(lambda: h.state() == "active", 30.0), h.state()
            wrenches = h.record("/cstomo_qemu/wrench", WrenchStamped)
            assert wait_for(lambda: len(wrenches) >= 1, 10.0)  # tared, publishing
            n0, f0 = len(wrenches), h.node.driver.stats().frames
            time.sleep(10.0)
            n1, st = len(wrenches), h.node.driver.stats()
        finally:
            h.close()
    frames, published = st.frames - f0, n1 - n0
    assert (st.seq_gaps, st.corrupt) == (0, 0), st
    assert frames >= 300, st  # the emulated board streams (it skips slots when QEMU lacks a core)
    assert published >= 0.95 * frames, (published, frames, st)
