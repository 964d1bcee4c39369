"""Modbus slave process for tests: pymodbus 3.16.1 with a datastore and faults we control.

Started by `tests.peers.PymodbusSlave` as `python tests/pymodbus_slave.py`. Protocol on
stdin/stdout (one JSON object a line):
  parent -> child, first line: the configuration (see PymodbusSlave.__init__)
  child -> parent:             `READY <port>` (tcp) / `READY <device>` (serial), or `FAILED`
  parent -> child, then:       {"op": ..., ...}; each gets one reply line
                               {"ok": true, "result": ...} or {"ok": false, "error": ...}
EOF on stdin stops the slave. Diagnostics go to stderr.

pymodbus does the framing (RTU or MBAP) and the PDU encoding; we replace two parts:
- the datastore: plain arrays per unit and area, served from address 0 (no SimData
  off-by-one), with exception ranges, offline units and request counters;
- the request handler: each request is handled with the PDU it came with (the stock
  handler re-reads `last_pdu` after awaiting), optionally after `response_delay`, and an
  unknown unit is really silent with ignore_missing_devices (stock 3.16.1 routes every
  request through SimCore, which answers an unknown unit with exception 4).
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
import traceback
from array import array
from collections import Counter
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from pymodbus.constants import ExcCodes
from pymodbus.exceptions import ModbusIOException, NoSuchIdException
from pymodbus.framer import FramerType
from pymodbus.pdu import ExceptionResponse, ModbusPDU
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice
from pymodbus.transaction import TransactionManager

from tests.peers import AREAS, BIT_AREAS, default_bit, default_register

#: Function code -> area it reads or writes.
FC_AREA: dict[int, str] = {
    1: "co", 5: "co", 15: "co",
    2: "di",
    3: "hr", 6: "hr", 16: "hr", 22: "hr", 23: "hr",
    4: "ir",
}  # fmt: skip


WRITE_FC = frozenset((5, 6, 15, 16, 22))


def log(message: str) -> None:
    """Diagnostics to stderr (the parent keeps them in a file)."""
    print(f"pymodbus_slave: {message}", file=sys.stderr, flush=True)


def emit(line: str) -> None:
    """One line to the parent."""
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


class Store:
    """Per unit, per area: an array of registers (`H`) or a bytearray of bits (0/1).

    Implements the two coroutines pymodbus' PDUs call on a datastore.
    """

    def __init__(self, cfg: dict[str, Any]) -> None:
        self.sizes: dict[str, int] = {a: int(n) for a, n in cfg["size"].items()}
        formula = cfg["fill"] == "formula"
        self.units: dict[int, dict[str, array[int] | bytearray]] = {
            int(unit): {area: self._fresh(int(unit), area, formula) for area in AREAS}
            for unit in cfg["units"]
        }
        for unit_s, areas in cfg["initial"].items():
            unit = int(unit_s)
            if unit not in self.units:
                raise ValueError(f"initial values for unit {unit}, which is not served")
            for area, values in areas.items():
                for address_s, value in values.items():
                    address = int(address_s)
                    self._check_range(area, address, 1)
                    self.units[unit][area][address] = int(value)
        self.offline: set[int] = set()
        self.ranges: list[dict[str, Any]] = list(cfg["exception_ranges"])
        self.delay: float = float(cfg["response_delay"])
        self.requests: Counter[int] = Counter()

    def _fresh(self, unit: int, area: str, formula: bool) -> array[int] | bytearray:
        n = self.sizes[area]
        if area in BIT_AREAS:
            if not formula:
                return bytearray(n)
            return bytearray(int(default_bit(unit, area, a)) for a in range(n))
        if not formula:
            return array("H", bytes(2 * n))
        return array("H", (default_register(unit, area, a) for a in range(n)))

    def _check_range(self, area: str, address: int, count: int) -> None:
        if area not in self.sizes:
            raise ValueError(f"unknown area {area!r}")
        if address < 0 or count < 0 or address + count > self.sizes[area]:
            raise ValueError(
                f"{area} {address}..{address + count - 1} outside 0..{self.sizes[area] - 1}"
            )

    def _check(self, unit: int, area: str, address: int, count: int) -> ExcCodes | None:
        """Exception code for a request, or None; NoSuchIdException for a missing unit."""
        if unit not in self.units or unit in self.offline:
            raise NoSuchIdException(f"unit {unit} is not here")
        end = address + count
        for rng in self.ranges:
            if rng["unit"] is not None and rng["unit"] != unit:
                continue
            if rng["area"] is not None and rng["area"] != area:
                continue
            if address < rng["end"] and end > rng["start"]:
                return ExcCodes(rng["code"])
        if end > self.sizes[area]:
            return ExcCodes.ILLEGAL_ADDRESS
        return None

    async def async_getValues(
        self, device_id: int, func_code: int, address: int, count: int = 1
    ) -> list[int] | list[bool] | ExcCodes:
        """Read for a PDU."""
        area = FC_AREA.get(func_code)
        if area is None:
            return ExcCodes.ILLEGAL_FUNCTION
        if (exc := self._check(device_id, area, address, count)) is not None:
            return exc
        data = self.units[device_id][area][address : address + count]
        if area in BIT_AREAS:
            return [bool(b) for b in data]
        return list(data)

    async def async_setValues(
        self, device_id: int, func_code: int, address: int, values: list[int] | list[bool]
    ) -> ExcCodes | None:
        """Write for a PDU."""
        area = FC_AREA.get(func_code)
        if area is None:
            return ExcCodes.ILLEGAL_FUNCTION
        values = list(values)
        if (exc := self._check(device_id, area, address, len(values))) is not None:
            return exc
        self.units[device_id][area][address : address + len(values)] = _as_array(area, values)
        return None

    def device_ids(self) -> list[int]:
        """Units served (pymodbus' broadcast path asks for them)."""
        return list(self.units)

    # control channel
    def get(self, unit: int, area: str, address: int, count: int) -> list[int]:
        """Values for the parent, without touching request counters or faults."""
        self._check_range(area, address, count)
        return list(self._unit(unit)[area][address : address + count])

    def set(self, unit: int, area: str, address: int, values: list[int]) -> None:
        """Overwrite values from the parent."""
        self._check_range(area, address, len(values))
        self._unit(unit)[area][address : address + len(values)] = _as_array(area, values)

    def _unit(self, unit: int) -> dict[str, array[int] | bytearray]:
        if unit not in self.units:
            raise ValueError(f"unit {unit} is not served (units: {sorted(self.units)})")
        return self.units[unit]


def _as_array(area: str, values: list[int] | list[bool]) -> array[int] | bytearray:
    if area in BIT_AREAS:
        return bytearray(int(bool(v)) for v in values)
    return array("H", (int(v) for v in values))


class App:
    """State shared by the server, its connection handlers and the control channel."""

    def __init__(self, cfg: dict[str, Any]) -> None:
        self.cfg = cfg
        self.store = Store(cfg)
        self.rtu = cfg["transport"] in ("rtu-over-tcp", "serial")
        self.ignore_missing = bool(cfg["ignore_missing_devices"])
        self.missing_code = ExcCodes(int(cfg["missing_unit_code"]))
        self.connections = 0
        self.responses = 0
        self.handlers: set[Handler] = set()
        self.per_connection: dict[str, int] = {}  # "<peer port>#<n>": its requests
        # per connection: its first and last request's arrival (time.monotonic(): one
        # clock for every process of the host) and its writes (FC 05, 06, 15, 16, 22)
        self.request_times: dict[str, list[float]] = {}
        self.writes: dict[str, int] = {}

    def control(self, msg: dict[str, Any]) -> Any:
        """Run one control command from the parent; returns its result."""
        op = msg.get("op")
        store = self.store
        if op == "get":
            return store.get(int(msg["unit"]), msg["area"], int(msg["address"]), int(msg["count"]))
        if op == "set":
            store.set(int(msg["unit"]), msg["area"], int(msg["address"]), list(msg["values"]))
            return None
        if op == "delay":
            store.delay = float(msg["seconds"])
            return None
        if op == "offline":
            unit = int(msg["unit"])
            store._unit(unit)
            if msg["offline"]:
                store.offline.add(unit)
            else:
                store.offline.discard(unit)
            return None
        if op == "exceptions":
            store.ranges = list(msg["ranges"])
            return None
        if op == "drop":
            handlers = list(self.handlers)
            for handler in handlers:
                handler.close()
            return len(handlers)
        if op == "stats":
            return {
                "requests": {str(k): v for k, v in store.requests.items()},
                "connections": self.connections,
                "active": len(self.handlers),
                "responses": self.responses,
                "perConnection": dict(self.per_connection),
                "activeConnections": sorted(h.name for h in self.handlers),
                "requestTimes": dict(self.request_times),
                "writesPerConnection": dict(self.writes),
            }
        if op == "ping":
            return "pong"
        raise ValueError(f"unknown op {op!r}")


class Handler(ServerRequestHandler):
    """One master connection (or the serial line): every request is served by its own
    task with the PDU it arrived with, after the configured delay."""

    def __init__(self, owner: Any, app: App) -> None:
        super().__init__(owner, None, None, None)
        self.app = app
        self.tasks: set[asyncio.Task[None]] = set()
        self.name = ""  # "<peer port>#<connection number>" once connected

    def callback_connected(self) -> None:
        """Count the connection."""
        super().callback_connected()
        self.app.connections += 1
        self.app.handlers.add(self)
        peer = self.transport.get_extra_info("peername") if self.transport else None
        port = peer[1] if isinstance(peer, tuple) and len(peer) > 1 else "serial"
        self.name = f"{port}#{self.app.connections}"
        self.app.per_connection[self.name] = 0

    def callback_disconnected(self, exc: Exception | None) -> None:
        """Forget the connection and its pending (delayed) answers."""
        super().callback_disconnected(exc)
        self.app.handlers.discard(self)
        for task in list(self.tasks):
            task.cancel()

    def close(self, reconnect: bool = False) -> None:
        """Hang up (control op "drop" or shutdown); connection_lost is then not called."""
        super().close(reconnect=reconnect)
        self.app.handlers.discard(self)
        for task in list(self.tasks):
            task.cancel()

    def callback_data(self, data: bytes, addr: tuple[Any, ...] | None = None) -> int:
        """Decode one frame and schedule its handling with that very PDU."""
        try:
            used_len: int = TransactionManager.callback_data(self, data, addr)
        except ModbusIOException as exc:
            response = ExceptionResponse(
                0x00 if exc.fcode is None else exc.fcode,
                exception_code=ExcCodes.ILLEGAL_FUNCTION,
                device_id=exc.dev_id,
                transaction=exc.transaction_id,
            )
            self.server_send(response, addr)
            return len(data)
        pdu = self.last_pdu
        if pdu is not None:
            task = asyncio.get_running_loop().create_task(self.serve(pdu, self.last_addr))
            self.tasks.add(task)
            task.add_done_callback(self.tasks.discard)
        return used_len

    async def serve(self, pdu: ModbusPDU, addr: tuple[Any, ...] | None) -> None:
        """Answer one request (or stay silent) after the response delay."""
        app = self.app
        store = app.store
        unit = pdu.dev_id
        store.requests[unit] += 1
        if self.name:
            app.per_connection[self.name] += 1
            now = time.monotonic()
            app.request_times.setdefault(self.name, [now, now])[1] = now
            if pdu.function_code in WRITE_FC:
                app.writes[self.name] = app.writes.get(self.name, 0) + 1
        if store.delay > 0:
            await asyncio.sleep(store.delay)  # pacing: the slave's configured response delay
        try:
            if app.rtu and unit == 0 and 0 not in store.units:
                # RTU broadcast: every unit executes it, nobody answers.
                for each in list(store.units):
                    if each not in store.offline:
                        await pdu.datastore_update(store, each)  # type: ignore[arg-type]
                return
            response = await pdu.datastore_update(store, unit)  # type: ignore[arg-type]
        except NoSuchIdException:
            if app.ignore_missing:
                return
            response = ExceptionResponse(pdu.function_code, app.missing_code)
        except Exception:
            log(f"request failed: {traceback.format_exc()}")
            response = ExceptionResponse(pdu.function_code, ExcCodes.DEVICE_FAILURE)
        response.transaction_id = pdu.transaction_id
        response.dev_id = unit
        if self.transport is None:
            return
        self.server_send(response, addr)
        app.responses += 1


def build_server(app: App) -> ModbusTcpServer | ModbusSerialServer:
    """A pymodbus server whose connections are served by our Handler."""
    cfg = app.cfg
    # pymodbus wants a datastore to construct; ours replaces it in Handler.serve.
    placeholder = SimDevice(id=1, simdata=SimData(0, datatype=DataType.REGISTERS))
    server: ModbusTcpServer | ModbusSerialServer
    if cfg["transport"] == "serial":
        server = ModbusSerialServer(
            placeholder,
            framer=FramerType.RTU,
            port=cfg["device"],
            baudrate=int(cfg["baudrate"]),
            parity=cfg["parity"],
            bytesize=int(cfg["bytesize"]),
            stopbits=int(cfg["stopbits"]),
            ignore_missing_devices=app.ignore_missing,
            reconnect_delay=0.0,
        )
    else:
        server = ModbusTcpServer(
            placeholder,
            framer=FramerType.RTU if cfg["transport"] == "rtu-over-tcp" else FramerType.SOCKET,
            address=(cfg["host"], int(cfg["port"])),
            ignore_missing_devices=app.ignore_missing,
        )
    server.callback_new_connection = lambda: Handler(server, app)  # type: ignore[method-assign]
    return server


async def listen(server: ModbusTcpServer | ModbusSerialServer, patience: float) -> bool:
    """Listen (bind with SO_REUSEADDR / open the device), retrying for `patience` s:
    a restart may find the port briefly taken or the pty not there yet."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + patience
    while True:
        if await server.listen():
            return True
        if loop.time() > deadline:
            return False
        await asyncio.sleep(0.05)  # poll: until it listens (deadline above)


async def reopen_serial(server: ModbusSerialServer) -> None:
    """Reopen the serial device when it went away (socat killed) and came back."""
    while True:
        await asyncio.sleep(0.1)  # pacing: checks the serial device now and then
        if not server.active_connections and await server.listen():
            log("serial device reopened")


async def main() -> int:
    """Read the configuration, serve, obey control commands until EOF on stdin."""
    loop = asyncio.get_running_loop()
    reader = asyncio.StreamReader(limit=1 << 26)
    stdin = open(0, "rb", buffering=0, closefd=False)  # noqa: SIM115 - lives as long as we do
    await loop.connect_read_pipe(lambda: asyncio.StreamReaderProtocol(reader), stdin)
    line = await reader.readline()
    if not line:
        return 1
    cfg = json.loads(line)
    try:
        app = App(cfg)
        server = build_server(app)
    except Exception:
        log(f"bad configuration: {traceback.format_exc()}")
        emit("FAILED")
        return 2
    if not await listen(server, float(cfg.get("bind_patience", 3.0))):
        where = cfg["device"] if cfg["transport"] == "serial" else (cfg["host"], cfg["port"])
        log(f"could not listen on {where}")
        emit("FAILED")
        return 3
    watchdog: asyncio.Task[None] | None = None
    if isinstance(server, ModbusSerialServer):
        emit(f"READY {cfg['device']}")
        watchdog = loop.create_task(reopen_serial(server))
    else:
        port = server.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]
        emit(f"READY {port}")
    while line := await reader.readline():
        try:
            reply = {"ok": True, "result": app.control(json.loads(line))}
        except Exception as exc:
            reply = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        emit(json.dumps(reply))
    if watchdog is not None:
        watchdog.cancel()
    for handler in list(app.handlers):
        handler.close()
    server.close()
    return 0


if __name__ == "__main__":
    sys.exit(asyncio.run(main()))
