"""Issue 24, "no traceback anywhere in the command line for bad input": a walk of the
argparse tree.  For every command and each of its options (and positional files), random
and known-bad values (empty, huge, negative, non-numeric, unknown names, missing files, a
folder, a FIFO, a nested or huge JSON file) end in one line per problem on stderr (stdout
for ``check``), naming the option, with exit code 2 for a usage error; never a
traceback, never a hang.  A value that happens to be valid runs the command against a
port that refuses on 127.0.0.1: exit code 0 or 1 (docs/command-line.md, "Exit codes").

Each call is ``edgemodbus.cli.main`` in a forked child (in-process: no interpreter
start-up per example) with a deadline; the long-running commands (demo, run, simulate)
get SIGINT at the deadline and must exit with 130.
"""

from __future__ import annotations

import argparse
import contextlib
import faulthandler
import json
import os
import select
import signal
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from edgemodbus.cli import build_parser, main
from tests.peers import free_port

LONG_RUNNING = {  # run until --seconds or Ctrl-C: what they print once running
    "demo": ("out", "simulator: "), "run": ("out", ""), "simulate": ("err", "serving slaves"),
}
DEADLINE = 20.0  # s for a command that should end by itself (a loaded 2-core machine)
GRACE = 20.0  # s after SIGINT
HUGE = 40 * 1024 * 1024  # bytes of the sparse "huge" file: above every file limit
FREE_TEXT = {  # options whose every value may be valid: the property is only "no traceback"
    ("import", "--device-code"), ("simulate", "--registration"), ("simulate", "--heartbeat"),
    ("simulate", "--seed"), ("action", "name"), ("action", "params"), ("templates", "name"),
    ("read", "address"), ("write", "address"), ("write", "value"),
}
MAX_LINE = 1000  # characters of an error line (a 5000-character value is shortened)
ANY_NUMBER = ("-5", "99999999999999999999")
VALID_NUMBERS = {  # the KNOWN_BAD numbers these options take
    ("read", "--multiplier"): ANY_NUMBER, ("write", "--multiplier"): ANY_NUMBER,
    ("scan", "--garbage-limit"): ("99999999999999999999",),  # never stop early, as 0
}
WRITTEN = {("import", "--output")}  # a new file is fine
FOLDERS = {("templates", "--dir")}  # an empty folder is fine
NO_RANDOM = {"--host", "--serial", "--dial"}  # random text could be a real name to resolve
KNOWN_BAD = ["", " ", "abc", "nosuchname", "x" * 5000, "\x00", "-5", "99999999999999999999",
             "1e400", "nan", "-inf"]


@dataclass(frozen=True)
class Files:
    device: Path  # a valid device file that polls a refusing port
    csv: Path  # a valid tag list
    missing: Path
    folder: Path
    fifo: Path
    nested: Path
    huge: Path
    invalid: Path
    scratch: Path  # the children's working directory (what -o writes lands here)
    closed_port: int

    def bad_paths(self) -> list[str]:
        return [str(p) for p in (self.missing, self.folder, self.fifo, self.nested,
                                 self.huge, self.invalid)]


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Files]:
    tmp = tmp_path_factory.mktemp("bad_input")
    port = free_port()
    device = tmp / "device.json"
    device.write_text(json.dumps({
        "organization": {"deviceCode": "D"},
        "communication": {"transport": "tcp", "tcpHost": "127.0.0.1", "tcpPort": port,
                          "readCycle": 200, "readTimeout": 200},
        "addressList": [{"name": "r", "address": "hr:0", "deviceDataType": "UInt16"}]}))
    csv = tmp / "tags.csv"
    csv.write_text("name,address,type\nr,hr:0,UInt16\n")
    fifo = tmp / "fifo"
    os.mkfifo(fifo)
    nested = tmp / "nested.json"
    nested.write_text("[" * 100_000 + "]" * 100_000)
    huge = tmp / "huge.json"
    with huge.open("wb") as f:
        f.truncate(HUGE)  # sparse: its size is what the limits look at
    invalid = tmp / "invalid.json"
    invalid.write_text("{not json")
    (tmp / "folder").mkdir()
    (tmp / "scratch").mkdir()
    yield Files(device, csv, tmp / "no-folder" / "missing.json", tmp / "folder", fifo, nested, huge,
                invalid, tmp / "scratch", port)  # missing: its folder too (-o cannot make it)


def base_argv(command: str, f: Files) -> tuple[list[str], list[str]]:
    """A call of ``command`` that is valid but for what the example replaces: its options
    (each takes one value) and its positionals."""
    refused = ["--host", "127.0.0.1", "--port", str(f.closed_port), "--timeout", "100"]
    return {
        "demo": (["--seconds", "0.5"], []),
        "run": (["--seconds", "1"], [str(f.device)]),
        "read": (refused, ["hr:0"]),
        "write": (refused, ["hr:0", "1"]),
        "plan": ([], [str(f.device)]),
        "check": ([], [str(f.device)]),
        "simulate": (["--port", "0", "--no-tcp"], []),
        "action": ([], [str(f.device)]),
        "descriptor": ([], []),
        "scan": (["--host", "127.0.0.1", "--port", str(f.closed_port), "--slaves", "1",
                  "--timeout", "50"], []),
        "templates": ([], []),
        "import": ([], [str(f.csv)]),
    }[command]


def command_parser(command: str) -> argparse.ArgumentParser:
    parser = build_parser(command)
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    found: argparse.ArgumentParser = sub.choices[command]
    return found


def value_actions(command: str) -> list[argparse.Action]:
    """The command's options and positionals that take a value."""
    return [a for a in command_parser(command)._actions
            if a.nargs != 0 and not isinstance(a, argparse._HelpAction)]


def name_of(action: argparse.Action) -> str:
    return action.option_strings[-1] if action.option_strings else action.dest


COMMANDS = sorted(next(a for a in build_parser()._actions
                       if isinstance(a, argparse._SubParsersAction)).choices)


def argv_with(command: str, action: argparse.Action, value: str, f: Files) -> list[str]:
    """The base call with ``value`` for ``action``: an option is added (replacing the
    base's value of it, or of an option it excludes), a positional replaces the base's
    (or follows them)."""
    options, positionals = base_argv(command, f)
    if not action.option_strings:
        dests = [a.dest for a in value_actions(command) if not a.option_strings]
        index = dests.index(action.dest)
        if index < len(positionals):
            positionals = [*positionals[:index], value, *positionals[index + 1:]]
        else:
            positionals = [*positionals, value]
        return [command, *options, "--", *positionals]
    drop = set(action.option_strings)
    for group in command_parser(command)._mutually_exclusive_groups:
        if action.dest in {a.dest for a in group._group_actions}:
            for other in group._group_actions:
                drop.update(other.option_strings)
    kept: list[str] = []
    words = iter(options)
    for word in words:
        if word in drop:
            next(words, None)  # every base option takes one value
        else:
            kept.append(word)
    return [command, *kept, f"{name_of(action)}={value}",
            *(["--", *positionals] if positionals else [])]


@dataclass
class Outcome:
    code: int
    out: str
    err: str
    interrupted: bool


def running(command: str, out: list[bytes], err: list[bytes]) -> bool:
    """Whether a long-running command printed that it runs (then SIGINT stops it)."""
    if command not in LONG_RUNNING:
        return False
    stream, marker = LONG_RUNNING[command]
    text = b"".join(out if stream == "out" else err)
    return bool(text) and marker.encode() in text


def stacks(pid: int, err_r: int) -> str:
    """The Python stacks of a child that hangs (faulthandler, on SIGUSR1)."""
    os.kill(pid, signal.SIGUSR1)
    text = b""
    end = time.monotonic() + 5
    while time.monotonic() < end and select.select([err_r], [], [], 0.5)[0]:
        data = os.read(err_r, 65536)
        if not data:
            break
        text += data
    return text.decode(errors="replace")


def call(argv: list[str], f: Files) -> Outcome:
    """``main(argv)`` in a forked child (stdin from /dev/null, its own process group, the
    scratch folder as its working directory).  A long-running command gets SIGINT as soon
    as it printed that it runs (a usage error ends it before that), or at the deadline;
    any other command ending after the deadline is a failure."""
    out_r, out_w = os.pipe()
    err_r, err_w = os.pipe()
    pid = child = os.fork()
    if pid == 0:  # the child: never returns
        code = 255
        try:
            os.setpgid(0, 0)
            os.chdir(tempfile.mkdtemp(dir=f.scratch))  # what -o abc writes stays there
            os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
            os.dup2(out_w, 1)
            os.dup2(err_w, 2)
            sys.stdout = open(1, "w", closefd=False)  # noqa: SIM115 (pytest captures sys.*)
            sys.stderr = open(2, "w", closefd=False)  # noqa: SIM115
            signal.signal(signal.SIGINT, signal.default_int_handler)
            faulthandler.register(signal.SIGUSR1, all_threads=True)  # a hang's stacks
            try:
                code = main(argv)
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None
                                                                   else 2)
            sys.stdout.flush()
            sys.stderr.flush()
        except BaseException:
            import traceback

            traceback.print_exc()
            sys.stderr.flush()
            code = 254
        os._exit(code)
    os.close(out_w)
    os.close(err_w)
    chunks: dict[int, list[bytes]] = {out_r: [], err_r: []}
    open_fds = {out_r, err_r}
    deadline = time.monotonic() + DEADLINE
    interrupted = False
    try:
        while open_fds:
            left = deadline - time.monotonic()
            if not interrupted and running(argv[0], chunks[out_r], chunks[err_r]):
                left = 0
            if left <= 0:
                if interrupted or argv[0] not in LONG_RUNNING:
                    raise AssertionError(f"{argv!r} did not end within {DEADLINE} s"
                                         + (f" (+{GRACE} s after SIGINT)" if interrupted
                                            else "") + "; its threads:\n"
                                         + stacks(pid, err_r))
                os.kill(pid, signal.SIGINT)
                interrupted = True
                deadline = time.monotonic() + GRACE
                continue
            ready, _, _ = select.select(list(open_fds), [], [], left)
            for fd in ready:
                data = os.read(fd, 65536)
                if data:
                    chunks[fd].append(data)
                else:
                    open_fds.discard(fd)
        _, status = os.waitpid(pid, 0)
        pid = 0
    finally:
        with contextlib.suppress(ProcessLookupError):  # the child and what it started
            os.killpg(child, signal.SIGKILL)
        if pid:
            os.waitpid(pid, 0)
        os.close(out_r)
        os.close(err_r)
    return Outcome(os.waitstatus_to_exitcode(status),
                   b"".join(chunks[out_r]).decode(errors="replace"),
                   b"".join(chunks[err_r]).decode(errors="replace"), interrupted)


def certainly_bad(command: str, action: argparse.Action, value: str, f: Files) -> bool:
    """Whether ``value`` is outside what ``action`` allows whatever else is given."""
    if (command, name_of(action)) in FREE_TEXT or action.option_strings == ["--log-format"]:
        return value not in (action.choices or [value])
    if action.choices is not None:
        return value not in action.choices
    unusable = ("", " ", "\x00", "x" * 5000)
    if name_of(action) in ("--host", "--dial"):
        return value in unusable or value in f.bad_paths()  # a path is no host name
    if (command, name_of(action)) in WRITTEN or name_of(action) == "--serial":
        return value in unusable or value in (str(f.folder), str(f.fifo))
    if (command, name_of(action)) in FOLDERS:
        return value != str(f.folder)
    if value in VALID_NUMBERS.get((command, name_of(action)), ()):
        return False
    return value in KNOWN_BAD or value in f.bad_paths()


def check(command: str, action: argparse.Action, value: str, f: Files) -> None:
    argv = argv_with(command, action, value, f)
    got = call(argv, f)
    said = got.err + (got.out if command == "check" else "")
    shown = (f"{[w[:100] for w in argv]!r}: exit {got.code}\nstdout: {got.out[-2000:]}\n"
             f"stderr: {got.err[-3000:]}")
    assert "Traceback" not in got.out + got.err, shown
    if got.interrupted:
        assert got.code == 130, shown
        assert not certainly_bad(command, action, value, f), shown
        return
    assert got.code in (0, 1, 2), shown
    if certainly_bad(command, action, value, f):
        assert got.code == 2, shown
    if got.code in (1, 2):
        problems = [line for line in said.splitlines() if line.strip()]
        assert problems, shown
        assert all(len(line) < MAX_LINE for line in problems), shown
    if got.code == 2 and action.option_strings:
        named = [s for s in action.option_strings if s in said]
        assert named or (command == "check"), shown


def known_values(command: str, action: argparse.Action, f: Files) -> list[str]:
    """The fixed values tried for ``action``: the known-bad ones and the bad paths (not
    the fixture files an option writes to: they would be overwritten)."""
    paths = f.bad_paths()
    if (command, name_of(action)) in WRITTEN:
        paths = [p for p in paths if p not in (str(f.nested), str(f.huge), str(f.invalid))]
    return [*KNOWN_BAD, *paths]


def values(command: str, action: argparse.Action, f: Files) -> st.SearchStrategy[str]:
    known = st.sampled_from([*known_values(command, action, f), "0", "-"])
    if name_of(action) in NO_RANDOM:
        return known
    return st.one_of(known, st.text(max_size=20),
                     st.integers(-(2**70), 2**70).map(str),
                     st.floats().map(repr))


@pytest.mark.timeout(600)
@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_refuses_bad_values_in_one_line(command: str, files: Files) -> None:
    """Every known-bad value of every option, then random ones (hypothesis)."""
    actions = value_actions(command)
    for action in actions:
        for value in known_values(command, action, files):
            check(command, action, value, files)

    @settings(max_examples=3 * len(actions), deadline=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(st.data())
    def random_values(data: st.DataObject) -> None:
        action = data.draw(st.sampled_from(actions))
        check(command, action, data.draw(values(command, action, files)), files)

    random_values()
