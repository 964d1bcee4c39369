"""edgemodbus.commission.scan_line against real peers: pymodbus slaves and our simulator,
on ptys joined by a UART model (tests/uart_line.py: a slave answers only at its own
settings, as on a real line) and over TCP (RTU over TCP, Modbus TCP)."""

from __future__ import annotations

from collections.abc import Callable, Iterator

import pytest

from edgemodbus.commission import Found, SettingDone, scan_line, serial_settings, setting_text
from edgemodbus.datatypes import Area
from edgemodbus.line.endpoint import TcpEndpoint
from edgemodbus.protocol import rtu
from edgemodbus.sim import Simulator
from tests.peers import ExceptionRange, PtyPair, PymodbusSlave
from tests.uart_line import UartLine, UartSettings

TIMEOUT = 0.25  # per probe: generous for a loaded machine (a pty answers in ~1 ms)

LineFactory = Callable[[str, UartSettings], UartLine]


@pytest.fixture
def uart_line() -> Iterator[LineFactory]:
    made: list[UartLine] = []

    def make(device: str, slave: UartSettings) -> UartLine:
        line = UartLine(device, slave).__enter__()
        made.append(line)
        return line

    yield make
    for line in made:
        line.close()


@pytest.fixture
def sim() -> Iterator[Simulator]:
    s = Simulator(slaves=[1, 2, 3, 4])
    yield s
    s.stop()


def run(*args: object, **kwargs: object) -> tuple[list[Found], list[SettingDone]]:
    found: list[Found] = []
    done: list[SettingDone] = []
    for event in scan_line(*args, **kwargs):  # type: ignore[arg-type]
        if isinstance(event, Found):
            found.append(event)
        elif isinstance(event, SettingDone):
            done.append(event)
    return found, done


def table(found: list[Found]) -> list[tuple[str, int, str]]:
    return [(setting_text(f.endpoint), f.slave_id, f.summary) for f in found]


@pytest.mark.parametrize("serial_slave", [{"units": (2,)}], indirect=True)
def test_pymodbus_slave_at_19200_8e1_found_only_there(
    serial_slave: PymodbusSlave, pty_pair: PtyPair, uart_line: LineFactory
) -> None:
    line = uart_line(pty_pair.a, UartSettings(19200, "E"))
    settings = serial_settings(line.path, [9600, 19200], ["N", "E"])
    found, done = run(settings, [1, 2, 3], timeout=TIMEOUT)
    assert table(found) == [("19200 8E1", 2, "FC03 ok")]
    by_setting = {setting_text(d.endpoint): d for d in done}
    assert list(by_setting) == ["9600 8N1", "9600 8E1", "19200 8N1", "19200 8E1"]
    # a wrong baud rate or parity here: the slave reads junk and stays silent, so no
    # garbage and no early stop; every id was probed once
    for name in ("9600 8N1", "9600 8E1", "19200 8N1"):
        d = by_setting[name]
        assert (d.ids_probed, d.probes, d.timeouts, d.garbage, d.replies) == (3, 3, 3, 0, 0)
        assert d.stopped_early is None
    assert line.garbled["to_slave"] > 0
    assert serial_slave.request_count(2) >= 1


@pytest.mark.parametrize("serial_slave", [{"units": (1, 2, 3)}], indirect=True)
def test_wrong_parity_stops_early_after_garbage(
    serial_slave: PymodbusSlave, pty_pair: PtyPair, uart_line: LineFactory
) -> None:
    """A slave at 8N1 reads a request sent at 8E1 (the parity bit falls on its stop bit)
    and answers; the master at 8E1 misreads the reply: garbage, 3 times, then the
    setting is given up, its other ids not probed."""
    line = uart_line(pty_pair.a, UartSettings(9600, "N"))
    settings = serial_settings(line.path, [9600], ["E", "N"])
    found, done = run(settings, range(1, 9), timeout=TIMEOUT, garbage_limit=3)
    wrong, right = done
    assert setting_text(wrong.endpoint) == "9600 8E1"
    assert (wrong.probes, wrong.garbage, wrong.replies, wrong.ids_probed) == (3, 3, 0, 3)
    assert wrong.stopped_early is not None and "wrong baud rate or parity" in wrong.stopped_early
    assert table(found) == [("9600 8N1", i, "FC03 ok") for i in (1, 2, 3)]
    assert right.stopped_early is None and right.ids_probed == 8
    assert line.garbled["to_master"] >= 3


@pytest.mark.parametrize("serial_slave", [{"units": (1,)}], indirect=True)
def test_wrong_baud_rate_stops_early_when_traffic_is_garbled(
    serial_slave: PymodbusSlave, pty_pair: PtyPair, uart_line: LineFactory
) -> None:
    """Another master polls at 19200 every 40 ms: at 9600 the scan hears its frames as
    junk and gives the setting up after 3 garbled replies, long before id 30."""
    line = uart_line(pty_pair.a, UartSettings(19200, "N"))
    other_master = rtu.frame(99, bytes([3, 0, 0, 0, 10]))
    line.talk(other_master, UartSettings(19200, "N"), 0.04)
    settings = serial_settings(line.path, [9600], ["N"])
    found, (done,) = run(settings, range(1, 31), timeout=TIMEOUT, garbage_limit=3)
    assert found == []
    assert done.garbage == 3 and done.replies == 0
    assert done.stopped_early is not None
    assert done.probes == done.garbage + done.timeouts == done.ids_probed < 30


def test_simulator_exception_replies_found_at_38400_8o1(
    sim: Simulator, uart_line: LineFactory
) -> None:
    """A device that answers with an exception is there: the next function is tried."""
    sim.slave(1).faults.refused_functions = frozenset({3})  # FC03: exception 01, FC04 ok
    sim.slave(2).faults.exception_ranges = [(Area.HOLDING_REGISTER, 0, 1, 2),
                                            (Area.INPUT_REGISTER, 0, 1, 2)]  # coils only
    sim.slave(3).faults.refused_functions = frozenset({1, 3, 4})  # exceptions only
    sim.remove_slave(4)
    path = sim.serve_pty(baudrate=38400)
    line = uart_line(path, UartSettings(38400, "O"))
    settings = serial_settings(line.path, [38400], ["E", "O"])
    found, done = run(settings, range(1, 6), timeout=TIMEOUT)
    assert table(found) == [
        ("38400 8O1", 1, "FC03 exception 01 (illegal function), FC04 ok"),
        ("38400 8O1", 2, "FC03 exception 02 (illegal data address), "
                         "FC04 exception 02 (illegal data address), FC01 ok"),
        ("38400 8O1", 3, "FC03 exception 01 (illegal function), FC04 exception 01 "
                         "(illegal function), FC01 exception 01 (illegal function)"),
    ]
    assert [d.replies for d in done] == [0, 2 + 3 + 3]


@pytest.mark.parametrize("transport", ["rtu-over-tcp", "tcp"])
def test_pymodbus_over_tcp(transport: str, slave_factory: Callable[..., PymodbusSlave]) -> None:
    slave = slave_factory(transport, units=(1, 3),
                          exception_ranges=[ExceptionRange(0, 1, code=2, area="hr", unit=3)])
    ep = TcpEndpoint("127.0.0.1", slave.port, transport)
    found, (done,) = run([ep], range(1, 5), timeout=TIMEOUT)
    assert table(found) == [
        (transport, 1, "FC03 ok"),
        (transport, 3, "FC03 exception 02 (illegal data address), FC04 ok"),
    ]
    assert (done.ids_probed, done.garbage, done.stopped_early) == (4, 0, None)


def test_simulator_rtu_over_tcp(sim: Simulator) -> None:
    sim.slave(2).faults.refused_functions = frozenset({3, 4})
    port = sim.serve_tcp("127.0.0.1", 0)
    ep = TcpEndpoint("127.0.0.1", port, "rtu-over-tcp")
    found, _ = run([ep], [2, 4, 5], timeout=TIMEOUT, functions=(3, 4, 1))
    assert table(found) == [
        ("rtu-over-tcp", 2, "FC03 exception 01 (illegal function), FC04 exception 01 "
                            "(illegal function), FC01 ok"),
        ("rtu-over-tcp", 4, "FC03 ok"),
    ]


def test_gateway_exception_for_an_absent_unit_is_not_a_device(
    slave_factory: Callable[..., PymodbusSlave]
) -> None:
    """A Modbus TCP gateway answers exception 0B (target failed to respond) for units
    with nothing behind them: well-formed replies, no device."""
    slave = slave_factory("tcp", units=(2,), ignore_missing_devices=False,
                          missing_unit_code=0x0B)
    found, (done,) = run([TcpEndpoint("127.0.0.1", slave.port, "tcp")], [1, 2, 3],
                         timeout=TIMEOUT)
    assert table(found) == [("tcp", 2, "FC03 ok")]
    assert (done.probes, done.replies, done.timeouts, done.garbage) == (3, 3, 0, 0)
    assert slave.request_count() == 3  # one probe each: FC04 is not tried after 0B


def test_peer_that_hangs_up_is_given_up_and_the_scan_goes_on(sim: Simulator) -> None:
    sim.slave(2).faults.close_every = 1  # closes the connection instead of answering
    port = sim.serve_tcp("127.0.0.1", 0)
    found, (done,) = run([TcpEndpoint("127.0.0.1", port, "rtu-over-tcp")], [2, 3],
                         timeout=TIMEOUT)
    assert table(found) == [("rtu-over-tcp", 3, "FC03 ok")]
    assert (done.closed, done.replies, done.ids_probed) == (1, 1, 2)
    assert sim.slave(2).stats()["requests"] == 2  # tried again once on a new connection
    assert sim.stats()["line"]["connections"] == 3


def test_closing_the_scan_closes_the_line(sim: Simulator) -> None:
    """Stopping a scan between two events (what Ctrl-C in the CLI does) closes the link
    at once; the leak check of conftest.py sees no socket or thread left."""
    port = sim.serve_tcp("127.0.0.1", 0)
    events = scan_line([TcpEndpoint("127.0.0.1", port, "rtu-over-tcp")], range(1, 248),
                       timeout=TIMEOUT)
    for event in events:
        if isinstance(event, Found):
            break
    events.close()
    assert sim.stats()["slaves"][1]["requests"] == 1


def test_bad_arguments_are_named() -> None:
    ep = TcpEndpoint("127.0.0.1", 502, "rtu-over-tcp")
    for kwargs, text in (
        ({"slave_ids": [0]}, "slave id 0: must be 1..247"),
        ({"slave_ids": [248]}, "slave id 248: must be 1..247"),
        ({"functions": (5,)}, "function 5"),
        ({"timeout": 0.0}, "timeout 0 s"),
        ({"garbage_limit": -1}, "garbage limit -1"),
    ):
        with pytest.raises(ValueError, match=text):
            next(scan_line([ep], **kwargs))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="parity 'X'"):
        serial_settings("/dev/null", [9600], ["X"])
    with pytest.raises(ValueError, match="stop bits 3"):
        serial_settings("/dev/null", [9600], ["N"], [3])
