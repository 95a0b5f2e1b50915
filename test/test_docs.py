"""Every command of README.md and docs/*.md that runs this package's tools names what exists: the
command lines in ``` blocks and the inline `code` that start with an entry point (``cstomo``,
``cstomo_sensor_node``, ``cstomo_sensor_host``, also as ``.venv/bin/cstomo``), ``ros2 run
cstomo_sensor`` or ``ros2 launch cstomo_sensor``. Each ``cstomo`` command is parsed by the parser
its subcommand really uses (:func:`cstomo_sensor.tools.cli.subcommand_parser`), options spelled out
in full; the node's ``-p name:=value`` are checked against its parameter table (name and type), the
launch's ``name:=value`` against the launch file's arguments. Placeholders in capitals (FILE, DIR, N)
stand for any value; an inline mention may leave out values and required options (`cstomo estimate
--reference`), a command in a block may not."""
from __future__ import annotations

import argparse
import re
import shlex
from pathlib import Path

import pytest
import yaml
from test_packaging import setup_keywords

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_]*$")  # FILE, DIR, N, NX, ...
ROS_FLAGS = {"--params-file": 1, "-r": 1, "--remap": 1, "--log-level": 1, "-e": 1, "--enclave": 1, "-p": 1, "--param": 1}


def entry_points() -> set[str]:
    return {e.split("=")[0].strip() for e in setup_keywords()["entry_points"]["console_scripts"]}


def commands(path: Path) -> list[tuple[int, str, bool]]:
    """(line, command, inline) of every command of ``path`` that runs one of this package's tools: the
    lines of ``` blocks (``\\`` continued) and the inline code of the text between them (also when
    it wraps onto the next line)."""
    out, block, pending, prose = [], False, "", []

    def inline_code():
        text = "\n".join(line for _, line in prose)
        out.extend((prose[0][0] + text.count("\n", 0, m.start()), " ".join(m[1].split()), True)
                   for m in re.finditer(r"`([^`]+)`", text))
        prose.clear()

    for n, line in enumerate(path.read_text().splitlines(), 1):
        if line.lstrip().startswith("```"):
            if not block and prose:
                inline_code()
            block = not block
        elif block:
            pending += line.strip().removeprefix("$ ")
            if pending.endswith("\\"):
                pending = pending[:-1] + " "
                continue
            out.append((n, pending, False))
            pending = ""
        else:
            prose.append((n, line))
    if prose:
        inline_code()
    return [(n, c, inline) for n, c, inline in out if _tool(_split(c)) is not None]


def _split(command: str) -> list[str]:
    """The words of a shell command, ``$(...)`` as one word, a trailing comment dropped."""
    try:
        return shlex.split(re.sub(r"\$\([^)]*\)", "PREFIX", command), comments=True)
    except ValueError:
        return []


def _tool(words: list[str]) -> tuple[str, list[str]] | None:
    """(the tool, its arguments) of a command that runs one of this package's tools, else None."""
    while words and re.match(r"^[A-Z_]+=", words[0]):  # VAR=value before the command
        words = words[1:]
    if words[:3] in (["ros2", "run", "cstomo_sensor"], ["ros2", "launch", "cstomo_sensor"]):
        return " ".join(words[:2]), words[3:]
    exe = re.match(r"^(?:\S*/(?:bin|lib/cstomo_sensor)/)?([\w-]+)$", words[0]) if words else None
    if exe and exe[1] in entry_points():  # cstomo, .venv/bin/cstomo, <prefix>/lib/cstomo_sensor/cstomo
        return exe[1], words[1:]
    return None


def _parse(parser: argparse.ArgumentParser, args: list[str], inline: bool) -> str | None:
    """Why ``args`` are not a command line of ``parser`` (None if they are). A synopsis (``[--opt X]``)
    or an elided command (``...``) is taken as an inline mention."""
    inline = inline or any(w == "..." or w.startswith("[") for w in args)
    args = [w.strip("[]") for w in args]
    actions = parser._option_string_actions
    filled, action, left = [], None, 0  # the option whose values are being read, how many it still needs
    for word in [w for w in args if w != "..."]:
        if word.startswith("-") and not re.match(r"^-[\d.]", word):
            if inline and left:  # a value left out in prose
                filled += [_value(action, "X")] * left
            name = word.split("=", 1)[0]
            if name not in actions:
                return f"{name} is not an option of {parser.prog}"
            action = actions[name]
            left = 0 if "=" in word or action.nargs == 0 else action.nargs if isinstance(action.nargs, int) else 1
            filled.append(word)
        else:
            filled.append(_value(action if left else None, word))
            left = max(left - 1, 0)
    if inline and left:
        filled += [_value(action, "X")] * left
    if "-h" in filled or "--help" in filled:
        return None

    class Refused(Exception):
        pass

    def error(message):
        raise Refused(message)

    parser.error = error
    try:
        parser.parse_args(filled)
    except Refused as err:
        if not (inline and "required" in str(err)):  # prose may leave out what a run needs
            return f"{parser.prog}: {err}"
    return None


def _value(action: argparse.Action | None, word: str) -> str:
    """A placeholder as a value the option takes (its first choice, a number), else the word."""
    if action is None or not PLACEHOLDER.match(word):
        return word
    if action.choices:
        return str(list(action.choices)[0])
    if action.type not in (None, str) and action.default is not None:  # a setting's flag: its default fits
        return str(action.default[0] if isinstance(action.default, list) else action.default)
    if action.type in (int, float):
        return "1"
    try:  # a checked number (tools.common.positive): 1 if it takes it
        return "1" if callable(action.type) and action.type("1") is not None else word
    except (argparse.ArgumentTypeError, ValueError, TypeError):
        return word


def _ros_args(words: list[str]) -> str | None:
    """Why the words after ``--ros-args`` are not the node's (None if they are)."""
    from cstomo_sensor.ros.params import PARAMETERS

    words = [w for w in words if w != "..."]
    i = 0
    while i < len(words):
        flag = words[i]
        if flag not in ROS_FLAGS or i + 1 >= len(words):
            return f"{flag}: not a ROS argument the docs use, or without its value"
        if flag in ("-p", "--param"):
            name, _, text = words[i + 1].partition(":=")
            if name not in PARAMETERS:
                return f"-p {name}: the node has no such parameter"
            default = PARAMETERS[name][0]
            value = yaml.safe_load(text) if text else None
            if not PLACEHOLDER.match(text) and type(value) is not type(default) and not (
                    isinstance(default, str) and not isinstance(value, (bool, list, dict))):
                return f"-p {name}:={text}: a {type(value).__name__}, the parameter is a {type(default).__name__}"
        i += 2
    return None


def _launch_arguments() -> set[str]:
    from cstomo_sensor.tools.launching import ARGUMENTS  # the launch file declares these

    return set(ARGUMENTS)


def check(command: str, inline: bool) -> str | None:
    """Why ``command`` names something that does not exist (None if everything it names does)."""
    from cstomo_sensor.errors import ConfigError
    from cstomo_sensor.tools.cli import subcommand_parser

    tool, args = _tool(_split(command))
    if tool == "ros2 launch":
        if not args or not (ROOT / "launch" / args[0]).is_file():
            return f"no launch file {args[:1]}"
        wrong = [a for a in args[1:] if a != "..." and not PLACEHOLDER.match(a.partition(":=")[0])
                 and a.partition(":=")[0] not in _launch_arguments()]
        return f"no launch arguments {wrong}" if wrong else None
    if tool == "ros2 run":
        if not args or args[0] not in entry_points():
            return f"no executable {args[:1]} in the package (entry points {sorted(entry_points())})"
        tool, args = args[0], args[1:]
    if tool == "cstomo":
        if not args or args == ["..."] or args[0] in ("-h", "--help"):
            return None  # the tool's name in prose, or its help
        try:
            parser, rest = subcommand_parser(args)
        except ConfigError as err:
            return str(err)
        return _parse(parser, rest, inline)
    own, ros = (args[:args.index("--ros-args")], args[args.index("--ros-args") + 1:]) if "--ros-args" in args else (args, [])
    if tool == "cstomo_sensor_node" and [w for w in own if w not in ("-h", "--help")]:
        return f"cstomo_sensor_node takes no arguments of its own but -h: {own}"
    if tool == "cstomo_sensor_host" and [w for w in own if not w.startswith("/") and not PLACEHOLDER.match(w)]:
        return f"cstomo_sensor_host takes namespaces: {own}"
    return _ros_args(ros)


def package_files(command: str) -> list[str]:
    """The package's files a command names by a relative path (``config/...``, ``scenes/...``, also as
    ``name:=config/...``)."""
    return [m[1] for w in _split(command) if (m := re.match(r"^(?:\w+:=)?((?:config|scenes)/\S+\.\w+)$", w))]


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_every_command_in_the_docs_names_real_commands_and_options(doc):
    from test_packaging import installed_files

    wrong = [f"{doc.name}:{n}: {c}\n    {why}" for n, c, inline in commands(doc) if (why := check(c, inline))]
    installed = installed_files()
    wrong += [f"{doc.name}:{n}: {c}\n    {f} is not installed (share/cstomo_sensor/{f})" for n, c, _ in commands(doc)
              for f in package_files(c) if f"share/cstomo_sensor/{f}" not in installed]
    assert not wrong, "\n".join(wrong)


def test_the_check_finds_what_does_not_exist():
    """The test above can fail: a flag, a subcommand, a parameter, an executable or a launch argument
    that does not exist, a placeholder where a number or choice is due is fine, a bad value is not."""
    assert len(commands(ROOT / "README.md")) >= 5 and any(inline for *_, inline in commands(ROOT / "README.md"))
    assert len(commands(ROOT / "docs" / "node.md")) > 20
    assert {Path(d).name for d in DOCS} >= {"README.md", "calibration.md", "node.md", "robot.md"}
    good = ["cstomo calibrate --reference ref.csv --frames frames.csv --forces forces.csv --out d.yaml",
            "OPENBLAS_NUM_THREADS=1 .venv/bin/cstomo bench --heldout N --out DIR",
            "cstomo estimate ... --estimator NAME", "cstomo model build --grid NX NY NZ",
            "ros2 run cstomo_sensor cstomo_sensor_node --ros-args --params-file F -p port:=/dev/cstomo -p rate_hz:=1000.0",
            "ros2 run cstomo_sensor cstomo board-sim --sensor cuboid_joint --rate 100 --load-script x.csv",
            "ros2 launch cstomo_sensor cstomo_sensor.launch.py sim:=true rviz:=true"]
    for c in good:
        assert check(c, inline=False) is None, (c, check(c, inline=False))
    assert check("cstomo estimate --reference", inline=True) is None  # prose: the flag alone
    assert package_files("ros2 launch cstomo_sensor cstomo_sensor.launch.py sensors:=config/x.yaml") == ["config/x.yaml"]
    bad = {"cstomo calibrate --bagfile b --out d.yaml": "--bagfile is not an option of cstomo calibrate",
           "cstomo calibrate --bag b --ou d.yaml": "--ou is not an option",  # no abbreviations
           "cstomo estimate --reference": "expected one argument",  # a command to run must be complete
           "cstomo estimate --reference r": "required: --frames, --out",
           "cstomo estimate --reference r --frames f --out o --estimator fastest": "invalid choice",
           "cstomo model compile": "'compile' is no subcommand",
           "cstomo bench --greit --drift --out DIR": "not allowed with",
           "ros2 run cstomo_sensor cstomo_sensor_node --ros-args -p rate:=100.0": "no such parameter",
           "ros2 run cstomo_sensor cstomo_sensor_node --ros-args -p rate_hz:=fast": "a str, the parameter is a float",
           "ros2 run cstomo_sensor cstomo_node": "no executable",
           "ros2 launch cstomo_sensor cstomo_sensor.launch.py rviz:=true gui:=true": "no launch arguments ['gui:=true']"}
    for c, why in bad.items():
        got = check(c, inline=False)
        assert got is not None and why in got, (c, got)


# --- README: one page whose commands run as printed ----------------------------------------------------

#: The README's commands that this test does not run, and why: the two set-up commands (the demo has its
#: own test, test_tools.py; `make test` is this suite) and the robot's ROS install (test_colcon_install.py).
NOT_RUN_HERE = {"make demo": "test_tools.py runs the demo", "make test": "this suite",
                "rosdep": "a ROS install", "python3 -m pip install --user": "a ROS install",
                "colcon build": "test_colcon_install.py", "ros2 launch": "a ROS install"}


def readme_blocks(path: Path = ROOT / "README.md") -> list[list[str]]:
    """The command lines of each ```bash block of ``path``, in order (``\\``-continued lines joined)."""
    blocks = re.findall(r"^```bash\n(.*?)^```", path.read_text(), re.S | re.M)
    out = []
    for block in blocks:
        lines, pending = [], ""
        for line in block.splitlines():
            pending += line.strip()
            if pending.endswith("\\"):
                pending = pending[:-1] + " "
                continue
            if pending:
                lines.append(pending)
            pending = ""
        out.append(lines)
    return out


def test_the_readme_fits_on_a_page_without_history():
    """README <= 150 lines a newcomer reads in five minutes: no commit hashes, no issue history; the line
    `.ci/run` stands for, and the two commands."""
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 150, len(text.splitlines())
    assert not re.search(r"\b[0-9a-f]{7,40}\b", text), re.search(r"\b[0-9a-f]{7,40}\b", text)
    assert not re.search(r"\bissues? \d+", text, re.I), re.search(r"\bissues? \d+", text, re.I)
    assert "make test   # set-up, then the whole test suite" in text and "make demo" in text
    assert "make test" in (ROOT / ".ci" / "run").read_text()
    # the activation comes before the first bare `cstomo` command of a block, and once
    lines = [ln for block in readme_blocks() for ln in block]
    first = next(i for i, ln in enumerate(lines) if ln.startswith("cstomo "))
    assert ". .venv/bin/activate" in lines[:first] and text.count(". .venv/bin/activate") == 1
    for doc in DOCS:  # one way in every document: the activated venv, never .venv/bin/cstomo
        assert ".venv/bin/cstomo" not in doc.read_text(), doc.name


def test_readme_blocks_are_found_and_the_ones_not_run_are_named():
    """The extraction above can fail: it finds the set-up, the activation and the replay, and every
    command it does not run is one of NOT_RUN_HERE."""
    lines = [ln for block in readme_blocks() for ln in block]
    assert lines[:2] == ["make demo   # set-up, then the simulated board + the node: live true vs estimated force",
                         "make test   # set-up, then the whole test suite"], lines[:2]
    assert ". .venv/bin/activate" in lines and any(ln.startswith("cstomo replay ") for ln in lines)
    assert readme_blocks(ROOT / "docs" / "protocol.md") == [] or all(readme_blocks(ROOT / "docs" / "protocol.md"))
    skipped = [ln for ln in lines if _not_run(ln)]
    assert len(skipped) == 6, skipped  # make demo, make test, the four robot lines


def _not_run(line: str) -> str | None:
    return next((why for start, why in NOT_RUN_HERE.items() if line.startswith(start)), None)


@pytest.mark.slow
def test_the_readme_commands_run_as_printed_in_order_on_a_fresh_copy(tmp_path):
    """A fresh copy of the repository's tracked files with the suite's .venv: the README's commands (all
    but NOT_RUN_HERE), run in order in one shell, as printed, no edit; then docs/faults.md's one-row run
    of its fault table, as the venv's `python` (before: `No module named 'rclpy'` with the system's)."""
    import os
    import shutil
    import subprocess
    import sys
    import time

    files = subprocess.run(["git", "-C", str(ROOT), "ls-files"], capture_output=True, text=True, check=True)
    clone = tmp_path / "clone"
    for name in files.stdout.splitlines():
        if (ROOT / name).is_file():
            (clone / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, clone / name)
    venv = Path(sys.executable).parent.parent
    (clone / ".venv").symlink_to(venv)  # what `make demo` made
    env = {k: v for k, v in os.environ.items() if k != "VIRTUAL_ENV"}  # PYTHONPATH: the code under test
    env["PATH"] = os.pathsep.join(p for p in env.get("PATH", "").split(os.pathsep) if not p.startswith(str(venv)))
    env.update(OPENBLAS_NUM_THREADS="1", ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
    assert shutil.which("cstomo", path=env["PATH"]) is None  # not on PATH before the activation
    lines = [ln for block in readme_blocks(clone / "README.md") for ln in block if not _not_run(ln)]
    shell = ["bash", "-euo", "pipefail", "-c"]
    script = "\n".join(f'echo "@@ $EPOCHREALTIME"\n{ln}' for ln in lines) + '\necho "@@ $EPOCHREALTIME"'
    t0 = time.monotonic()
    r = subprocess.run([*shell, script], cwd=clone, env=env, capture_output=True, text=True, timeout=600)
    marks = [float(ln.split()[1].replace(",", ".")) for ln in r.stdout.splitlines() if ln.startswith("@@ ")]
    assert r.returncode == 0, f"{r.stdout}\n{r.stderr}"
    assert len(marks) == len(lines) + 1, marks
    print(f"README's commands: {time.monotonic() - t0:.0f} s",
          *(f"{b - a:6.1f} s  {ln}" for a, b, ln in zip(marks, marks[1:], lines)), sep="\n")
    assert "usage: cstomo" in r.stdout  # cstomo --help, after the activation
    assert "200 frames from /cstomo_sensor/raw_voltages: 190 results written to out/replayed_bag" in r.stdout
    assert (clone / "out" / "planar" / "truth.csv").is_file()
    assert re.search(r"wrote out/planar/forces.csv: \d+ forces", r.stdout), r.stdout
    header = (clone / "out" / "planar" / "forces.csv").read_text().splitlines()[0]
    assert header.startswith("frame,fx,fy,fz,magnitude,elevation_deg,azimuth_deg"), header
    # docs/faults.md: its one-row run, in the activated venv
    faults = (ROOT / "docs" / "faults.md").read_text()
    one_row = re.search(r"`(python test/fault_table.py stall)`", faults)[1]
    r = subprocess.run([*shell, f". .venv/bin/activate\n{one_row}"], cwd=clone, env=dict(env, ROS_DOMAIN_ID="93"),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.startswith("| stall"), r.stdout + r.stderr
