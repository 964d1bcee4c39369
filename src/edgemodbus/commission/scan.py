"""Find what answers on a line: sweep serial settings, probe slave ids.

:func:`scan_line` takes the line's candidate settings (serial ports at each baud rate,
parity and stop bits of :func:`serial_settings`, or one TCP endpoint) and the slave ids
to try, and yields what happens as it goes (:data:`ScanEvent`): a setting begins, a
device answered, one more id probed (progress), a setting is done (with its counts and,
if it was cut short, why).  It runs on the caller's thread: one link at a time, opened
by the line layer (:func:`edgemodbus.line.connect.open_link`), which keeps the line's
timing (the t3.5 silence between frames of Modbus over Serial Line v1.02, 2.5.1.1, and
settles the line after a timeout so that a late reply is never taken for the next
answer).  Closing the generator (or an exception in it, KeyboardInterrupt included)
closes the link: no thread and no open port is left behind.

The probe of one slave id: a read of one item at address 0 with each function of
``functions`` in turn (FC03, then FC04, then FC01 by default):

* a normal reply: the device is there, the probe of this id ends;
* an exception reply: the device is there (Modbus Application Protocol v1.1b3, 7),
  the next function is tried (a device without holding registers may have input
  registers or coils);
* exception 0A or 0B (gateway path unavailable, gateway target failed to respond): a
  gateway answered for a device that is not there (Application Protocol v1.1b3, 7):
  a well-formed reply, but nothing at this id;
* the peer closed the connection (a TCP gateway that hangs up on an unknown unit): the
  link is reopened and the read tried once more; closed again, the id is given up
  (result ``closed``) and the next one probed on a new connection;
* no reply to the first function: nothing at this id (a device that does not
  implement a function answers exception 01; waiting for FC04 and FC01 too would
  triple the time of every empty id);
* garbage: bytes that are not a reply to the request (a frame with a bad CRC, a wrong
  slave id, function or byte count, or bytes that stop short of a whole frame): counted
  for the setting, the probe of this id ends.

Early stop (serial settings and TCP transports alike): once ``garbage_limit`` probes of
one setting got garbage and none got a well-formed reply, the setting is taken for the
wrong one (bytes arrive, but at another baud rate, parity or framing) and its remaining
ids are skipped.  A setting with one well-formed reply is never cut short: garbage there
is noise on a line that works.  ``garbage_limit=0`` disables the rule.

What a wrong setting looks like on a line (a UART receiving at other settings than the
sender's): at a wrong parity with the right baud rate, a slave set to no parity still
reads the request (the parity bit falls where it expects the stop bit) and answers, and
the master misreads the reply: garbage, so the setting stops after ``garbage_limit``
devices answered.  At a wrong baud rate the slave reads junk and stays silent, so the
master hears garbage only when something else talks on the line (another master still
polling, a device that sends on its own): then that setting stops early too; on a quiet
line every id of it is probed and times out.  Scan with no other master on the line:
its traffic at the right setting is well-formed but not ours (another slave id), which
counts as garbage as well.
"""

from __future__ import annotations

from collections.abc import Generator, Iterable, Sequence
from dataclasses import dataclass, field

from ..datatypes import Area
from ..errors import (
    IncompleteReplyError,
    ModbusConnectionError,
    ModbusExceptionResponse,
    ModbusTimeoutError,
    ProtocolError,
)
from ..line.connect import open_link
from ..line.endpoint import LineTiming, SerialPort, TcpEndpoint
from ..line.link import Link
from ..protocol.limits import MAX_SLAVE_ID, MAX_UNIT_ID
from ..stats import LineStats

ScanEndpoint = SerialPort | TcpEndpoint

DEFAULT_PROBES: tuple[int, ...] = (3, 4, 1)
"""Function codes tried on each slave id, in order: holding, input registers, coils."""
PARITIES = ("N", "E", "O")
STOP_BITS = (1, 2)
DEFAULT_GARBAGE_LIMIT = 3
SERIAL_TIMEOUT = 0.1  # seconds per probe at 9600 baud and above
TCP_TIMEOUT = 0.5  # a DTU's serial side behind a mobile network adds some 100 ms
GATEWAY_CODES = frozenset({0x0A, 0x0B})  # the gateway speaks for an absent device


@dataclass(frozen=True)
class Answer:
    """What one read got: ``result`` is ``ok``, ``exception`` (``code`` and its
    ``detail``, e.g. "illegal data address"), ``timeout``, ``garbage`` or ``closed``
    (``detail``: what was wrong)."""

    function: int
    result: str
    code: int | None = None
    detail: str = ""

    @property
    def well_formed(self) -> bool:
        """A reply that answers the request (normal or exception)."""
        return self.result in ("ok", "exception")

    @property
    def device_there(self) -> bool:
        """A device answered: any well-formed reply but a gateway's for an absent one."""
        return self.result == "ok" or (self.result == "exception"
                                       and self.code not in GATEWAY_CODES)

    def text(self) -> str:
        if self.result == "exception":
            return f"FC{self.function:02d} exception {self.code:02d} ({self.detail})"
        return f"FC{self.function:02d} {self.result}"

    def as_dict(self) -> dict[str, object]:
        out: dict[str, object] = {"function": self.function, "result": self.result}
        if self.result == "exception":
            out["exceptionCode"] = self.code
            out["exception"] = self.detail
        elif self.detail:
            out["detail"] = self.detail
        return out


@dataclass(frozen=True)
class SettingStarted:
    """The scan of ``endpoint`` (setting ``index`` of ``count``) begins."""

    endpoint: ScanEndpoint
    index: int
    count: int


@dataclass(frozen=True)
class Found:
    """A device answered (a normal or an exception reply) at ``slave_id``."""

    endpoint: ScanEndpoint
    slave_id: int
    answers: tuple[Answer, ...]

    @property
    def summary(self) -> str:
        """e.g. "FC03 exception 02 (illegal data address), FC04 ok"."""
        return ", ".join(a.text() for a in self.answers)


@dataclass(frozen=True)
class Progress:
    """``done`` of ``total`` (settings x ids) are behind us; ids skipped by an early
    stop count as done."""

    endpoint: ScanEndpoint
    slave_id: int
    done: int
    total: int


@dataclass
class SettingDone:
    """The end of one setting: probes sent, well-formed replies, garbage, timeouts,
    connections the peer closed, ids probed, and ``stopped_early`` (why the rest was
    skipped) or None."""

    endpoint: ScanEndpoint
    probes: int = 0
    replies: int = 0
    garbage: int = 0
    timeouts: int = 0
    closed: int = 0
    ids_probed: int = 0
    stopped_early: str | None = None
    found: list[int] = field(default_factory=list)


ScanEvent = SettingStarted | Found | Progress | SettingDone


def setting_text(endpoint: ScanEndpoint) -> str:
    """A setting as people write it: "19200 8E1", or the TCP transport."""
    if isinstance(endpoint, SerialPort):
        return f"{endpoint.baudrate} {endpoint.data_bits}{endpoint.parity}{endpoint.stop_bits}"
    return endpoint.transport


def serial_settings(port: str, baudrates: Iterable[int], parities: Iterable[str] = ("N",),
                    stop_bits: Iterable[int] = (1,), *, rs485: str = "none",
                    echo: bool = False) -> list[SerialPort]:
    """The serial settings to sweep, baud rate first, then parity, then stop bits (8 data
    bits: RTU, Serial Line 2.5.1).  A bad value raises ValueError naming it."""
    out: list[SerialPort] = []
    bauds = list(baudrates)
    pars = [p.upper() for p in parities]
    stops = list(stop_bits)
    for name, values in (("baud rate", bauds), ("parity", pars), ("stop bits", stops)):
        if not values:
            raise ValueError(f"{name}: give at least one")
    for baud in bauds:
        if not 50 <= baud <= 4_000_000:
            raise ValueError(f"baud rate {baud}: must be 50..4000000")
    for parity in pars:
        if parity not in PARITIES:
            raise ValueError(f"parity {parity!r}: must be one of N, E, O")
    for stop in stops:
        if stop not in STOP_BITS:
            raise ValueError(f"stop bits {stop}: must be 1 or 2")
    for baud in dict.fromkeys(bauds):
        for parity in dict.fromkeys(pars):
            for stop in dict.fromkeys(stops):
                out.append(SerialPort(port, baud, parity, 8, stop, rs485=rs485, echo=echo))
    return out


def default_timeout(endpoint: ScanEndpoint) -> float:
    """Seconds to wait for a probe's reply: 100 ms at 9600 baud and above, longer in
    proportion below (1200 baud: 0.8 s; the request alone takes 67 ms there); 0.5 s on
    TCP."""
    if isinstance(endpoint, SerialPort):
        return SERIAL_TIMEOUT * max(1.0, 9600 / endpoint.baudrate)
    return TCP_TIMEOUT


def scan_line(endpoints: Sequence[ScanEndpoint],
              slave_ids: Iterable[int] = range(1, MAX_SLAVE_ID + 1), *,
              functions: Sequence[int] = DEFAULT_PROBES, address: int = 0,
              timeout: float | None = None, garbage_limit: int = DEFAULT_GARBAGE_LIMIT,
              request_interval: float = 0.0) -> Generator[ScanEvent, None, None]:
    """Probe ``slave_ids`` at each of ``endpoints`` in turn; yield what happens (see the
    module's text for the probe and the early stop).  ``timeout``: seconds per probe
    (None: :func:`default_timeout` of each setting).  Raises ValueError for a bad
    argument before any I/O, and :class:`ModbusConnectionError` when a line cannot be
    opened (or reopened after the peer closed it)."""
    eps = list(endpoints)
    if not eps:
        raise ValueError("settings: give at least one endpoint to scan")
    ids = list(dict.fromkeys(slave_ids))
    _check_arguments(eps, ids, functions, address, timeout, garbage_limit, request_interval)
    total = len(eps) * len(ids)
    for index, ep in enumerate(eps):
        yield SettingStarted(ep, index, len(eps))
        wait = default_timeout(ep) if timeout is None else timeout
        prober = _Prober(ep, _timing(ep, wait, request_interval))
        done = SettingDone(ep)
        try:
            for n, slave in enumerate(ids, 1):
                answers = prober.probe(slave, functions, address, done)
                done.ids_probed += 1
                if any(a.device_there for a in answers):
                    done.found.append(slave)
                    yield Found(ep, slave, tuple(answers))
                if garbage_limit and done.garbage >= garbage_limit and not done.replies:
                    wrong = "baud rate or parity" if isinstance(ep, SerialPort) else "transport"
                    done.stopped_early = (f"{done.garbage} garbled replies and no well-formed "
                                          f"one: wrong {wrong}")
                yield Progress(ep, slave, index * len(ids) + n, total)
                if done.stopped_early:
                    break
        finally:
            prober.close()
        if done.stopped_early:
            yield Progress(ep, ids[-1], (index + 1) * len(ids), total)
        yield done


def _check_arguments(eps: list[ScanEndpoint], ids: list[int], functions: Sequence[int],
                     address: int, timeout: float | None, garbage_limit: int,
                     request_interval: float) -> None:
    if not ids:
        raise ValueError("slave ids: give at least one")
    for ep in eps:
        if not isinstance(ep, (SerialPort, TcpEndpoint)):
            raise ValueError(f"{ep!r}: scan a serial port or a TCP endpoint")
        tcp = isinstance(ep, TcpEndpoint) and ep.transport == "tcp"
        low, high = (0, MAX_UNIT_ID) if tcp else (1, MAX_SLAVE_ID)
        bad = [i for i in ids if not low <= i <= high]
        if bad:
            raise ValueError(f"slave id {bad[0]}: must be {low}..{high} on {setting_text(ep)}"
                             + (" (0 is the broadcast address)" if low else ""))
    if not functions:
        raise ValueError("functions: give at least one")
    for fc in functions:
        if fc not in (1, 2, 3, 4):
            raise ValueError(f"function {fc}: a probe reads with FC01, FC02, FC03 or FC04")
    if not 0 <= address <= 0xFFFF:
        raise ValueError(f"address {address}: must be 0..65535")
    if timeout is not None and not 0.001 <= timeout <= 60:
        raise ValueError(f"timeout {timeout:g} s: must be 0.001..60 s")
    if garbage_limit < 0:
        raise ValueError(f"garbage limit {garbage_limit}: must be 0 (never stop early) or more")
    if not 0 <= request_interval <= 10:
        raise ValueError(f"request interval {request_interval:g} s: must be 0..10 s")


def _timing(ep: ScanEndpoint, wait: float, request_interval: float) -> LineTiming:
    """The line timing of a scan: the probe's timeout, also as the settle time after a
    timeout (a slow device's late reply is thrown away, not taken for the next id's),
    and a byte timeout of 20 characters (at least 20 ms) on serial lines."""
    byte_timeout = max(0.02, 20 * ep.char_time) if isinstance(ep, SerialPort) else 0.2
    return LineTiming(response_timeout=wait, byte_timeout=byte_timeout, settle_timeout=wait,
                      connect_timeout=max(3.0, wait), request_interval=request_interval)


class _Prober:
    """The open link of one setting; reopened once when it breaks."""

    def __init__(self, ep: ScanEndpoint, timing: LineTiming) -> None:
        self.ep = ep
        self.timing = timing
        self.stats = LineStats()
        self.link: Link = open_link(ep, timing, self.stats)

    def close(self) -> None:
        self.link.close()

    def probe(self, slave: int, functions: Sequence[int], address: int,
              done: SettingDone) -> list[Answer]:
        answers: list[Answer] = []
        for fc in functions:
            answer = self._read(slave, fc, address)
            done.probes += 1
            answers.append(answer)
            if answer.well_formed:
                done.replies += 1
            elif answer.result == "garbage":
                done.garbage += 1
            elif answer.result == "closed":
                done.closed += 1
            else:
                done.timeouts += 1
            if answer.device_there and answer.result == "exception":
                continue  # the device is there: another function may answer normally
            if answer.result == "timeout" and any(a.device_there for a in answers):
                continue  # it answered an earlier function
            break
        return answers

    def _read(self, slave: int, fc: int, address: int) -> Answer:
        for attempt in (1, 2):
            if not self.link.is_open:
                self._reopen()
            try:
                self.link.read(slave, Area(fc), address, 1)
            except ModbusExceptionResponse as exc:
                return Answer(fc, "exception", exc.code, exc.label)
            except IncompleteReplyError as exc:
                return Answer(fc, "garbage", None, str(exc))
            except ModbusTimeoutError:
                return Answer(fc, "timeout")
            except ProtocolError as exc:
                return Answer(fc, "garbage", None, str(exc))
            except ModbusConnectionError as exc:
                self.link.close()
                if attempt == 2:
                    return Answer(fc, "closed", None, str(exc))
                continue
            return Answer(fc, "ok")
        raise AssertionError("unreachable")  # pragma: no cover

    def _reopen(self) -> None:
        """A new link; raises ModbusConnectionError if the line cannot be opened."""
        self.link.close()
        self.link = open_link(self.ep, self.timing, self.stats)
