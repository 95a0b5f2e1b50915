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


@pytest.mark.slow  # runs the cross-compiler
@pytest.mark.parametrize("table", [True, False], ids=["emulated", "hardware"])
def test_the_image_fits_a_64k_flash_16k_ram_part(tmp_path, table):
    text, data, bss = elf_size(build_stm32(tmp_path, table=table))  # the linker script is 64k/16k as well
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
