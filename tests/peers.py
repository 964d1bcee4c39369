"""Independent Modbus peers for integration tests.

`PymodbusSlave` runs pymodbus 3.16.1 as a Modbus slave in its OWN process
(tests/pymodbus_slave.py), so that its CPU is not counted as ours in benchmarks and a
test can kill and restart it. It serves RTU framing over TCP, Modbus TCP, or serial RTU
on a pty. `PtyPair` wraps `socat` to make a pair of linked ptys (a null-modem cable).

This module imports neither pytest nor pymodbus: the slave process imports the default
value formulas from here, and tests use them to compute what the slave should answer.
"""

from __future__ import annotations

import contextlib
import json
import os
import select
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, Literal

__all__ = [
    "AREAS",
    "SLAVE_SCRIPT",
    "ExceptionRange",
    "PeerError",
    "PtyPair",
    "PymodbusSlave",
    "Transport",
    "default_bit",
    "default_register",
    "free_port",
    "normalize_area",
]

Transport = Literal["rtu-over-tcp", "tcp", "serial"]
TRANSPORTS: tuple[str, ...] = ("rtu-over-tcp", "tcp", "serial")

#: Canonical area names: coils, discrete inputs, holding registers, input registers.
AREAS: tuple[str, ...] = ("co", "di", "hr", "ir")
BIT_AREAS: frozenset[str] = frozenset({"co", "di"})
REGISTER_AREAS: frozenset[str] = frozenset({"hr", "ir"})

_AREA_ALIASES: dict[str, str] = {
    "co": "co", "c": "co", "coil": "co", "coils": "co", "1": "co",
    "di": "di", "d": "di", "discreteinput": "di", "discreteinputs": "di",
    "discrete_input": "di", "discrete_inputs": "di", "2": "di",
    "hr": "hr", "h": "hr", "holding": "hr", "holdingregister": "hr",
    "holdingregisters": "hr", "holding_registers": "hr", "3": "hr",
    "ir": "ir", "i": "ir", "input": "ir", "inputregister": "ir",
    "inputregisters": "ir", "input_registers": "ir", "4": "ir",
}  # fmt: skip

#: Exception codes pymodbus can answer (its `ExcCodes` enum).
VALID_EXCEPTION_CODES: frozenset[int] = frozenset({1, 2, 3, 4, 5, 6, 7, 8, 0x0A, 0x0B})

SLAVE_SCRIPT: Path = Path(__file__).resolve().with_name("pymodbus_slave.py")
_REPO_ROOT: Path = SLAVE_SCRIPT.parent.parent


class PeerError(RuntimeError):
    """A test peer could not start, died, or refused a control command."""


def normalize_area(area: str) -> str:
    """Map an area name or alias (`coil`, `holding`, `3`, ...) to `co|di|hr|ir`."""
    try:
        return _AREA_ALIASES[str(area).strip().lower()]
    except KeyError:
        raise ValueError(f"unknown Modbus area {area!r}; use one of {AREAS}") from None


def default_register(unit: int, area: str, address: int) -> int:
    """Initial value of a holding/input register in a `PymodbusSlave`.

    Derived from the unit and the address so that a read from the wrong unit, area or
    offset shows up as a wrong value: holding `(unit*1000 + address) & 0xFFFF`, input
    registers the same plus 0x8000 (so FC03 and FC04 never agree).
    """
    area = normalize_area(area)
    if area == "hr":
        return (unit * 1000 + address) & 0xFFFF
    if area == "ir":
        return (unit * 1000 + address + 0x8000) & 0xFFFF
    raise ValueError(f"{area!r} is a bit area; use default_bit()")


def default_bit(unit: int, area: str, address: int) -> bool:
    """Initial value of a coil/discrete input: coils `(unit+address) % 3 == 0`,
    discrete inputs `(unit+address) % 4 == 1` (different patterns per area and unit)."""
    area = normalize_area(area)
    if area == "co":
        return (unit + address) % 3 == 0
    if area == "di":
        return (unit + address) % 4 == 1
    raise ValueError(f"{area!r} is a register area; use default_register()")


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago (bind port 0, read it, close).

    Racy by nature; prefer letting the server bind port 0 itself (PymodbusSlave does).
    Useful for "nothing listens there" tests.
    """
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port


@dataclass(frozen=True)
class ExceptionRange:
    """Requests touching addresses `start <= a < end` are answered with exception `code`.

    `area` None means every area, `unit` None every unit. The first matching range wins;
    ranges are checked before the datastore size (beyond which the answer is code 2).
    """

    start: int
    end: int
    code: int = 2
    area: str | None = None
    unit: int | None = None

    def __post_init__(self) -> None:
        if not 0 <= self.start < self.end <= 0x10000:
            raise ValueError(f"need 0 <= start < end <= 65536, got {self.start}..{self.end}")
        if self.code not in VALID_EXCEPTION_CODES:
            raise ValueError(f"exception code {self.code} is not one pymodbus can send")
        if self.area is not None:
            object.__setattr__(self, "area", normalize_area(self.area))

    def to_json(self) -> dict[str, Any]:
        """The form the slave process receives."""
        return {
            "start": self.start,
            "end": self.end,
            "code": self.code,
            "area": self.area,
            "unit": self.unit,
        }


class _LineReader:
    """Reads newline-terminated lines from a pipe fd with a timeout, without threads."""

    def __init__(self, fd: int) -> None:
        self._fd = fd
        self._buf = b""

    def readline(self, timeout: float) -> bytes | None:
        """One line without its newline; None at EOF; TimeoutError after `timeout` s."""
        deadline = time.monotonic() + timeout
        poller = select.poll()
        poller.register(self._fd, select.POLLIN | select.POLLHUP | select.POLLERR)
        while b"\n" not in self._buf:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError("no line from the peer in time")
            if not poller.poll(max(1, int(remaining * 1000))):
                continue
            chunk = os.read(self._fd, 65536)
            if not chunk:
                return None
            self._buf += chunk
        line, _, self._buf = self._buf.partition(b"\n")
        return line


SizeSpec = int | Mapping[str, int]
InitialSpec = Mapping[int, Mapping[str, Mapping[int, int | bool]]]


class PymodbusSlave:
    """A pymodbus 3.16.1 slave in a subprocess, driven from the test process.

    transport:
      - "rtu-over-tcp": RTU frames over a TCP stream (a DTU / serial server), 127.0.0.1
      - "tcp": Modbus TCP (MBAP header), 127.0.0.1
      - "serial": RTU on a serial device, normally one end of a `PtyPair`
    units: the unit ids served. Any other unit stays silent when `ignore_missing_devices`
      (like a real RS-485 line), else gets exception `missing_unit_code` (default 4, what
      stock pymodbus 3.16.1 answers).
    size: registers/bits per area (int, or {area: n}); address 0 is readable; a request
      reaching `size` or beyond gets exception 2.
    fill: "formula" (see default_register/default_bit) or "zero"; `initial` overrides
      single addresses: {unit: {area: {address: value}}}.
    response_delay: seconds the slave waits before answering EVERY request (a slave that
      answers after the master's timeout); changeable at run time.
    exception_ranges: ExceptionRange list, answered with their exception code.
    bind_patience: seconds the child keeps retrying a busy port / a missing device.

    The datastore lives in the child and is reset by restart(). Use as a context manager
    (starts on enter, stops on exit) or call start()/stop().
    """

    def __init__(
        self,
        transport: Transport = "rtu-over-tcp",
        *,
        units: Sequence[int] = (1,),
        host: str = "127.0.0.1",
        port: int = 0,
        device: str | os.PathLike[str] | None = None,
        baudrate: int = 19200,
        parity: str = "N",
        bytesize: int = 8,
        stopbits: int = 1,
        master_path: str | os.PathLike[str] | None = None,
        ignore_missing_devices: bool = True,
        missing_unit_code: int = 4,
        size: SizeSpec = 10_000,
        fill: Literal["formula", "zero"] = "formula",
        initial: InitialSpec | None = None,
        response_delay: float = 0.0,
        exception_ranges: Sequence[ExceptionRange] = (),
        start_timeout: float = 60.0,
        control_timeout: float = 10.0,
        bind_patience: float = 3.0,
    ) -> None:
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
        if transport == "serial" and device is None:
            raise ValueError("transport 'serial' needs device= (e.g. PtyPair.b)")
        if not units:
            raise ValueError("units must not be empty")
        for unit in units:
            if not 0 <= unit <= 255:
                raise ValueError(f"unit id {unit} out of 0..255")
        if missing_unit_code not in VALID_EXCEPTION_CODES:
            raise ValueError(f"missing_unit_code {missing_unit_code} is not a Modbus code")
        if fill not in ("formula", "zero"):
            raise ValueError("fill must be 'formula' or 'zero'")
        if response_delay < 0:
            raise ValueError("response_delay must be >= 0")
        self.transport: Transport = transport
        self.units: tuple[int, ...] = tuple(units)
        self.host = host
        self.device: str | None = None if device is None else os.fspath(device)
        #: The path the master should open (informational; set by the serial fixtures).
        self.master_path: str | None = None if master_path is None else os.fspath(master_path)
        self.start_timeout = start_timeout
        self.control_timeout = control_timeout
        self._requested_port = port
        self._port: int | None = None
        self._config: dict[str, Any] = {
            "transport": transport,
            "host": host,
            "device": self.device,
            "baudrate": baudrate,
            "parity": parity,
            "bytesize": bytesize,
            "stopbits": stopbits,
            "units": list(self.units),
            "ignore_missing_devices": ignore_missing_devices,
            "missing_unit_code": missing_unit_code,
            "size": _size_json(size),
            "fill": fill,
            "initial": _initial_json(initial or {}),
            "response_delay": float(response_delay),
            "exception_ranges": [r.to_json() for r in exception_ranges],
            "bind_patience": float(bind_patience),
        }
        self._proc: subprocess.Popen[bytes] | None = None
        self._stderr: IO[bytes] | None = None
        self._reader: _LineReader | None = None
        self._last_stderr = ""

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> PymodbusSlave:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> PymodbusSlave:
        """Start the child and wait for `READY`; raises PeerError with its stderr."""
        if self.running:
            raise PeerError("slave already running")
        self._cleanup()
        port = self._port if self._port is not None else self._requested_port
        config = dict(self._config, port=port)
        self._stderr = tempfile.TemporaryFile(  # noqa: SIM115 - closed in _cleanup()
            prefix="pymodbus-slave-", suffix=".log"
        )
        env = dict(os.environ)
        env["PYTHONUNBUFFERED"] = "1"
        env["PYTHONPATH"] = os.pathsep.join(
            p for p in (str(_REPO_ROOT), env.get("PYTHONPATH", "")) if p
        )
        proc = subprocess.Popen(
            [sys.executable, str(SLAVE_SCRIPT)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._stderr,
            bufsize=0,
            start_new_session=True,  # Ctrl-C in the terminal stops pytest, not the peer
            env=env,
            cwd=str(_REPO_ROOT),
        )
        self._proc = proc
        assert proc.stdout is not None
        self._reader = _LineReader(proc.stdout.fileno())
        try:
            self._write_line(json.dumps(config))
            line = self._reader.readline(self.start_timeout)
        except TimeoutError:
            self._abort()
            raise PeerError(
                f"pymodbus slave not ready after {self.start_timeout}s; stderr:\n"
                f"{self._last_stderr}"
            ) from None
        except PeerError:
            self._abort()
            raise PeerError(f"pymodbus slave died at start; stderr:\n{self._last_stderr}") from None
        if line is None or not line.startswith(b"READY"):
            self._abort()
            raise PeerError(
                f"pymodbus slave failed to start ({line!r}); stderr:\n{self._last_stderr}"
            )
        parts = line.decode().split()
        if self.transport != "serial":
            self._port = int(parts[1])
        return self

    def stop(self, timeout: float = 3.0) -> None:
        """Stop gracefully (EOF on its stdin), then SIGTERM, then SIGKILL; always reap."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            if proc.stdin is not None:
                with contextlib.suppress(OSError):
                    proc.stdin.close()
            try:
                proc.wait(timeout)
            except subprocess.TimeoutExpired:
                proc.terminate()
                try:
                    proc.wait(timeout)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
        self._cleanup()

    def kill(self) -> None:
        """SIGKILL the slave (a crash: sockets are reset by the kernel) and reap it."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        self._cleanup()

    def restart(self) -> PymodbusSlave:
        """Start again on the SAME port (or device) after stop()/kill(); datastore resets.

        The child binds with SO_REUSEADDR (pymodbus' create_server sets it) and retries
        a busy port for a short while, so TIME_WAIT leftovers do not matter.
        """
        if self.running:
            self.stop()
        return self.start()

    @property
    def running(self) -> bool:
        """True while the child process is alive."""
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        """The child's pid while it exists."""
        return None if self._proc is None else self._proc.pid

    @property
    def port(self) -> int:
        """TCP port the slave listens on (kept across restart())."""
        if self._port is None:
            raise PeerError(f"no TCP port ({self.transport} slave not started?)")
        return self._port

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) for a TCP master."""
        return (self.host, self.port)

    @property
    def stderr_text(self) -> str:
        """What the child wrote to stderr so far (last run after stop())."""
        if self._stderr is not None:
            return _read_all(self._stderr)
        return self._last_stderr

    # ------------------------------------------------------------------ datastore
    def registers(self, unit: int, area: str = "hr", address: int = 0, count: int = 1) -> list[int]:
        """Current values of `count` registers in the slave's datastore (no Modbus I/O)."""
        area = _register_area(area)
        result = self._call("get", unit=unit, area=area, address=address, count=count)
        return [int(v) for v in result]

    def bits(self, unit: int, area: str = "co", address: int = 0, count: int = 1) -> list[bool]:
        """Current values of `count` coils/discrete inputs in the slave's datastore."""
        area = _bit_area(area)
        result = self._call("get", unit=unit, area=area, address=address, count=count)
        return [bool(v) for v in result]

    def set_registers(self, unit: int, area: str, address: int, values: Sequence[int]) -> None:
        """Overwrite registers (any register area, input registers too)."""
        area = _register_area(area)
        vals = [int(v) for v in values]
        if any(not 0 <= v <= 0xFFFF for v in vals):
            raise ValueError("register values must be 0..65535")
        self._call("set", unit=unit, area=area, address=address, values=vals)

    def set_bits(self, unit: int, area: str, address: int, values: Sequence[bool]) -> None:
        """Overwrite coils/discrete inputs."""
        area = _bit_area(area)
        bits = [int(bool(v)) for v in values]
        self._call("set", unit=unit, area=area, address=address, values=bits)

    # ------------------------------------------------------------------ faults and stats
    def set_response_delay(self, seconds: float) -> None:
        """Answer every request from now on `seconds` late (0 = at once)."""
        if seconds < 0:
            raise ValueError("delay must be >= 0")
        self._call("delay", seconds=float(seconds))

    def set_offline(self, unit: int, offline: bool = True) -> None:
        """Make one unit behave as missing (silent, or missing_unit_code) or come back."""
        self._call("offline", unit=unit, offline=bool(offline))

    def set_exception_ranges(self, ranges: Sequence[ExceptionRange]) -> None:
        """Replace the exception ranges."""
        self._call("exceptions", ranges=[r.to_json() for r in ranges])

    def drop_connections(self) -> int:
        """Close every open master connection (the DTU hangs up); returns how many."""
        return int(self._call("drop"))

    def stats(self) -> dict[str, Any]:
        """Counters since start: {"requests": {unit: n}, "connections": total accepted,
        "active": open now, "responses": answers sent, "perConnection": {name: requests},
        "activeConnections": [name], "requestTimes": {name: [first, last]} (arrivals on
        time.monotonic()), "writesPerConnection": {name: writes}}."""
        raw = self._call("stats")
        raw["requests"] = {int(k): int(v) for k, v in raw["requests"].items()}
        return dict(raw)

    def request_count(self, unit: int | None = None) -> int:
        """Requests received (for one unit, or all, served or not) since start."""
        requests: dict[int, int] = self.stats()["requests"]
        return requests.get(unit, 0) if unit is not None else sum(requests.values())

    # ------------------------------------------------------------------ internals
    def _call(self, op: str, **args: Any) -> Any:
        if not self.running or self._reader is None:
            raise PeerError(f"slave is not running (stderr:\n{self.stderr_text})")
        self._write_line(json.dumps({"op": op, **args}))
        try:
            line = self._reader.readline(self.control_timeout)
        except TimeoutError:
            raise PeerError(f"slave did not answer control op {op!r}") from None
        if line is None:
            raise PeerError(f"slave died during {op!r}; stderr:\n{self.stderr_text}")
        reply = json.loads(line)
        if not reply.get("ok"):
            raise PeerError(f"slave refused {op!r}: {reply.get('error')}")
        return reply.get("result")

    def _write_line(self, text: str) -> None:
        proc = self._proc
        if proc is None or proc.stdin is None:
            raise PeerError("slave is not running")
        data = (text + "\n").encode()
        try:
            while data:
                written = proc.stdin.write(data)
                data = data[written or 0 :]
        except (BrokenPipeError, ValueError, OSError) as exc:
            raise PeerError(f"slave's control pipe is closed ({exc})") from None

    def _abort(self) -> None:
        """Kill a child that failed to start and keep its stderr for the message."""
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.kill()
        if proc is not None:
            proc.wait()
        self._cleanup()

    def _cleanup(self) -> None:
        """Close our ends of the pipes and the stderr file of a dead child."""
        proc = self._proc
        if proc is not None:
            if proc.poll() is None:  # pragma: no cover - callers reap first
                proc.kill()
                proc.wait()
            for stream in (proc.stdin, proc.stdout):
                if stream is not None:
                    with contextlib.suppress(OSError):
                        stream.close()
        if self._stderr is not None:
            self._last_stderr = _read_all(self._stderr)
            self._stderr.close()
            self._stderr = None
        self._proc = None
        self._reader = None

    def __repr__(self) -> str:
        where = self.device if self.transport == "serial" else f"{self.host}:{self._port}"
        state = "running" if self.running else "stopped"
        return f"<PymodbusSlave {self.transport} {where} units={list(self.units)} {state}>"


def _read_all(stream: IO[bytes]) -> str:
    stream.flush()
    stream.seek(0)
    return stream.read().decode(errors="replace")


def _register_area(area: str) -> str:
    canon = normalize_area(area)
    if canon not in REGISTER_AREAS:
        raise ValueError(f"{area!r} is not a register area (hr/ir); use bits()/set_bits()")
    return canon


def _bit_area(area: str) -> str:
    canon = normalize_area(area)
    if canon not in BIT_AREAS:
        raise ValueError(f"{area!r} is not a bit area (co/di); use registers()")
    return canon


def _size_json(size: SizeSpec) -> dict[str, int]:
    if isinstance(size, int):
        sizes = dict.fromkeys(AREAS, size)
    else:
        sizes = dict.fromkeys(AREAS, 10_000)
        sizes.update({normalize_area(k): int(v) for k, v in size.items()})
    for area, n in sizes.items():
        if not 1 <= n <= 0x10000:
            raise ValueError(f"size of {area} must be 1..65536, got {n}")
    return sizes


def _initial_json(initial: InitialSpec) -> dict[str, dict[str, dict[str, int]]]:
    out: dict[str, dict[str, dict[str, int]]] = {}
    for unit, areas in initial.items():
        for area, values in areas.items():
            canon = normalize_area(area)
            dest = out.setdefault(str(int(unit)), {}).setdefault(canon, {})
            for address, value in values.items():
                v = int(value)
                if canon in BIT_AREAS:
                    v = int(bool(value))
                elif not 0 <= v <= 0xFFFF:
                    raise ValueError(f"initial value {value} at {canon}:{address} not 0..65535")
                dest[str(int(address))] = v
    return out


def _die_with_parent() -> None:
    """In the forked child: ask Linux for SIGTERM when our parent goes away."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):  # pragma: no cover - not Linux/glibc
        pass


class PtyPair:
    """Two linked ptys made by `socat -d -d pty,raw,echo=0,link=A pty,raw,echo=0,link=B`.

    What is written to `a` is read from `b` and back: the master opens one end, the
    serial slave the other. `unplug()` kills socat (the USB adapter disappears: the
    links vanish and open fds see EOF/EIO); `replug()` starts it again with the same link
    names (new /dev/pts behind them). `close()` stops socat for good.

    socat gets SIGTERM if the thread that started it ends (PR_SET_PDEATHSIG), so a
    killed pytest leaves no socat behind: start it from a thread that outlives it.
    """

    def __init__(
        self,
        directory: str | os.PathLike[str],
        a_name: str = "ttyA",
        b_name: str = "ttyB",
        timeout: float = 5.0,
    ) -> None:
        self.directory = Path(directory)
        self.a = str(self.directory / a_name)
        self.b = str(self.directory / b_name)
        self.timeout = timeout
        self._proc: subprocess.Popen[bytes] | None = None
        self._log: IO[bytes] | None = None

    def __enter__(self) -> PtyPair:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def running(self) -> bool:
        """True while socat is alive."""
        return self._proc is not None and self._proc.poll() is None

    @property
    def pid(self) -> int | None:
        """socat's pid while it exists."""
        return None if self._proc is None else self._proc.pid

    def start(self) -> PtyPair:
        """Run socat and wait until both links exist."""
        if self.running:
            raise PeerError("socat already running")
        self._reap()
        self.directory.mkdir(parents=True, exist_ok=True)
        for path in (self.a, self.b):
            if os.path.islink(path) or os.path.exists(path):
                os.unlink(path)  # stale link of a killed socat
        self._log = tempfile.TemporaryFile(prefix="socat-", suffix=".log")  # noqa: SIM115 - _reap()
        self._proc = subprocess.Popen(
            [
                "socat", "-d", "-d",
                f"pty,raw,echo=0,link={self.a}",
                f"pty,raw,echo=0,link={self.b}",
            ],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=self._log,
            start_new_session=True,
            preexec_fn=_die_with_parent,
        )  # fmt: skip
        deadline = time.monotonic() + self.timeout
        while not (os.path.exists(self.a) and os.path.exists(self.b)):
            if self._proc.poll() is not None or time.monotonic() > deadline:
                log = _read_all(self._log)
                self._stop_process(kill=True)
                raise PeerError(f"socat did not create {self.a} and {self.b}:\n{log}")
            time.sleep(0.01)  # poll: until socat made both ends (deadline above)
        return self

    def unplug(self) -> None:
        """The adapter disappears: SIGKILL socat and remove the links it leaves behind."""
        self._stop_process(kill=True)
        for path in (self.a, self.b):
            if os.path.islink(path):
                os.unlink(path)

    def replug(self) -> PtyPair:
        """The adapter comes back under the same names (new ptys behind them)."""
        if self.running:
            self.unplug()
        return self.start()

    def close(self) -> None:
        """Stop socat (SIGTERM, it removes its links; SIGKILL if it hangs) and reap it."""
        self._stop_process(kill=False)
        for path in (self.a, self.b):
            if os.path.islink(path):
                os.unlink(path)

    def _stop_process(self, *, kill: bool) -> None:
        proc = self._proc
        if proc is not None and proc.poll() is None:
            if kill:
                proc.kill()
            else:
                proc.terminate()
            try:
                proc.wait(3.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._reap()

    def _reap(self) -> None:
        if self._proc is not None and self._proc.poll() is None:  # pragma: no cover
            self._proc.kill()
            self._proc.wait()
        self._proc = None
        if self._log is not None:
            self._log.close()
            self._log = None

    def __repr__(self) -> str:
        return f"<PtyPair {self.a} <-> {self.b} {'running' if self.running else 'stopped'}>"
