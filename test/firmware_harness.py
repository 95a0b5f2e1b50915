"""Building and running the board's reference firmware (firmware/) for the tests: the host build with
the machine's ``cc`` (optionally under AddressSanitizer and UBSan), the Cortex-M4F image with
``arm-none-eabi-gcc`` and its QEMU run. Each build goes to a temporary folder, never into the tree."""
from __future__ import annotations

import re
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
FIRMWARE = ROOT / "firmware"
CORE = sorted((FIRMWARE / "core").glob("*.c"))
HOST = sorted((FIRMWARE / "host").glob("*.c"))
STM32 = sorted((FIRMWARE / "stm32").glob("*.c"))
ARM_PACKAGES = "gcc-arm-none-eabi picolibc-arm-none-eabi"
QEMU_PACKAGE = "qemu-system-arm"


def need_cc() -> str:
    cc = shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")
    if cc is None:
        pytest.skip("no C compiler (cc): the host firmware cannot be built (Debian: apt-get install gcc)")
    return cc


def build_host(out_dir: Path, sanitize: bool = False) -> Path:
    """The host firmware built with cc into ``out_dir``; its path."""
    cc = need_cc()
    exe = Path(out_dir) / ("cstomo-fw-host-asan" if sanitize else "cstomo-fw-host")
    flags = ["-std=c11", "-O2", "-Wall", "-Wextra", "-Werror"]
    if sanitize:
        flags += ["-g", "-fsanitize=address,undefined", "-fno-sanitize-recover=undefined", "-fno-omit-frame-pointer"]
    subprocess.run([cc, *flags, "-o", str(exe), *map(str, CORE + HOST), "-lm"], check=True, capture_output=True,
                   text=True)
    return exe


def need_arm() -> str:
    gcc = shutil.which("arm-none-eabi-gcc")
    specs = Path("/usr/lib/picolibc/arm-none-eabi/picolibc.specs")
    if gcc is None or not specs.exists():
        pytest.skip(f"no arm-none-eabi-gcc with picolibc: the Cortex-M4F image is not built (Debian: apt-get install "
                    f"{ARM_PACKAGES})")
    return gcc


def build_stm32(out_dir: Path, frames_c: Path | None = None, table: bool = True) -> Path:
    """The Cortex-M4F image (table front-end unless ``table`` is False) built into ``out_dir``."""
    gcc = need_arm()
    elf = Path(out_dir) / ("cstomo-fw-stm32.elf" if table else "cstomo-fw-stm32-hw.elf")
    frames_c = frames_c or FIRMWARE / "stm32" / "frames_table.c"
    flags = ["-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16", "-std=c11", "-Os", "-g", "-Wall",
             "-Wextra", "-Werror", "-ffunction-sections", "-fdata-sections", "--specs=picolibc.specs", "-nostartfiles",
             "-T", str(FIRMWARE / "stm32" / "stm32f4.ld"), "-Wl,--gc-sections"]
    if table:
        flags.append("-DCSTOMO_FRONTEND_TABLE")
    stm32 = [p for p in STM32 if p.name != "frames_table.c"]
    subprocess.run([gcc, *flags, "-o", str(elf), *map(str, CORE + stm32), str(frames_c)], check=True,
                   capture_output=True, text=True)
    return elf


def elf_size(elf: Path) -> tuple[int, int, int]:
    """(text, data, bss) of ``arm-none-eabi-size`` (bss includes the stack)."""
    out = subprocess.run(["arm-none-eabi-size", str(elf)], check=True, capture_output=True, text=True).stdout
    text, data, bss = map(int, out.splitlines()[1].split()[:3])
    return text, data, bss


def write_frames(path: Path, rows: np.ndarray) -> Path:
    np.savetxt(path, np.atleast_2d(rows), fmt="%.9e", delimiter=",", header="test frames", comments="# ")
    return path


class Process:
    """A firmware process (host build, or QEMU) whose first line names the device; stopped on exit."""

    def __init__(self, argv: list[str], device_pattern: str = r"device: (\S+)", timeout: float = 20.0) -> None:
        self.proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + timeout
        self.device = None
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if not line:
                break
            m = re.search(device_pattern, line)
            if m:
                self.device = m.group(1)
                break
        if self.device is None:
            self.stop()
            raise RuntimeError(f"{argv[0]} named no device: {self.proc.stderr.read()}")

    def stop(self) -> str:
        """Stop (SIGTERM, then SIGKILL) and return what it said on stderr."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        return self.proc.stderr.read() if self.proc.stderr else ""

    def __enter__(self) -> Process:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()


def qemu_argv(elf: Path, debug_file: Path) -> list[str]:
    """QEMU's netduinoplus2 (an STM32F405) with USART1 on a new pty and USART2 into ``debug_file``."""
    if shutil.which("qemu-system-arm") is None:
        pytest.skip(f"no qemu-system-arm: the image is not booted (Debian: apt-get install {QEMU_PACKAGE})")
    return ["qemu-system-arm", "-M", "netduinoplus2", "-nographic", "-monitor", "none", "-serial", "pty",
            "-serial", f"file:{debug_file}", "-kernel", str(elf)]
