"""DriverModbusRtu: one Modbus device (slave) polled on a shared line.

The contract (docs/library.md): start, stop, hot update of the address list, writes
(blocking and asyncio), callbacks, subscribers, status, snapshot and stats.  This module
is a facade: it checks the configuration, acquires the line (:mod:`edgemodbus.line`) and
hands it a :class:`~edgemodbus.poll.poller.Poller`, which plans, decodes, keeps item
state and isolates faults on the line's worker thread.  The poller reports through a
sink (:class:`~edgemodbus.poll.sink.PollSink`) the driver gives it, never through the
driver itself; subscribers are listeners (poll/listeners.py) behind the batch callback.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping, Sequence
from concurrent.futures import Future
from typing import Any, ClassVar

from .config import (
    DeviceAction,
    DeviceAddressItem,
    DeviceOrganizationParameter,
    DriverModbusRtuParameter,
    device_enabled,
    effective_parameters,
    validate_actions,
    validate_items,
    validate_parameters,
)
from .config.listen import key_bytes, networks
from .datatypes import DeviceDriverStatus
from .errors import ModbusConnectionError
from .line import (
    DtuAccess,
    DtuEndpoint,
    DtuRegistry,
    DtuSlot,
    Endpoint,
    LineRegistry,
    LineTiming,
    LineWorker,
    PortSettings,
    dtu_registry,
    endpoint_for,
    line_registry,
)
from .poll.actions import find_action, plan_action, prefix_errors
from .poll.listeners import BatchCallbackListener, Listener, Subscribers
from .poll.poller import Poller
from .poll.schedule import block_dict, entity_numbers_notice
from .poll.sink import BatchCallback, ItemCallback, SnapshotPublisher
from .poll.store import check_free
from .poll.writes import WriteOp, plan_writes
from .protocol.forward import check_request


class DriverModbusRtu:
    """A Modbus RTU / RTU-over-TCP / Modbus TCP device driver (one slave).

    Drivers whose lines are the same (same serial port, or same host:port) share one
    line worker; that is how many slaves on one RS-485 line are polled.
    """

    logger: ClassVar[logging.Logger] = logging.getLogger("edgemodbus.driver")
    registry: ClassVar[LineRegistry] = line_registry
    dtu_registry: ClassVar[DtuRegistry] = dtu_registry

    def __init__(self) -> None:
        self.address_updated_callback: ItemCallback | None = None
        self.addresses_updated_callback: BatchCallback | None = None
        self.snapshot_publisher: SnapshotPublisher | None = None
        self._subscribers: Subscribers[DriverModbusRtu] = Subscribers(
            BatchCallbackListener(lambda: self.addresses_updated_callback))
        self._poller: Poller | None = None
        self._last_poller: Poller | None = None  # keeps stats and snapshot after a stop
        self._line: LineWorker | None = None
        self._slot: DtuSlot | None = None  # listen mode: this device's DTU
        self._line_stats: dict[str, Any] = {}
        self._status = DeviceDriverStatus.STOPPED
        self._params: DriverModbusRtuParameter | None = None
        self._org: DeviceOrganizationParameter | None = None
        self._enabled = False
        self._actions: list[DeviceAction] = []

    # -- lifecycle ---------------------------------------------------------------------
    def start_device(
        self,
        org_param: DeviceOrganizationParameter | None,
        comm_param: DriverModbusRtuParameter,
        addresses: Sequence[DeviceAddressItem],
        actions: Sequence[DeviceAction] = (),
    ) -> bool:
        """Start polling (``actions``: the device file's, for :meth:`run_action`).
        Returns True when polling started; False when the device is
        disabled (status ``Disabled``) or the driver is already running (nothing done).
        Raises ``ValueError`` (a :class:`ConfigError` for the configuration, naming the
        item, field, value and what is allowed) or a line already open with other serial
        settings.  Everything is checked (items, codec specs, read plan, endpoint) before
        a line is acquired: a failed start leaves no thread, socket or line behind."""
        if self._poller is not None:
            self.logger.warning("%s: start_device: already running", self._code(org_param))
            return False
        validate_parameters(org_param, comm_param)
        params = effective_parameters(org_param, comm_param)
        enabled = device_enabled(org_param, comm_param)
        code = _device_code(org_param, params)
        if not enabled:
            self._org, self._params, self._enabled = org_param, params, False
            self._status = DeviceDriverStatus.DISABLED
            self.logger.info("%s: disabled, not polled", code)
            return False
        parsed = validate_items(list(addresses), params)
        validate_actions(actions, parsed)
        check_free(addresses)  # ItemInUseError: an item polled by a running driver
        self._actions = list(actions)
        endpoint, timing = endpoint_for(params), _timing(params)
        # builds the items' codec specs, the plan and its decoders: raises here, not
        # after the line's worker is running
        poller = Poller(_Sink(self), code, params, parsed, self.logger)
        notice = entity_numbers_notice(parsed, params)
        if notice is not None:
            self.logger.warning("%s: %s", code, notice)
        if params.read_cycle == 0 and params.framing != "wrapped-report":
            self.logger.warning("%s: readCycle 0 means report-only, but framing is %r: nothing "
                                "will update this device's items", code, params.framing)
        # ours before the line runs the poller: its first callbacks and snapshot come at once
        before = self._org, self._params, self._enabled
        self._poller = poller
        self._org, self._params, self._enabled = org_param, params, True
        try:
            line, slot = self._acquire(params, endpoint, timing, poller)
        except BaseException:
            self._poller = None
            self._org, self._params, self._enabled = before
            raise
        self._slot = slot
        self._line, self._last_poller = line, None
        self._status = DeviceDriverStatus.CONNECTING
        self.logger.info(
            "%s: polling slave %d on %s every %d ms (%d items, %d blocks)",
            poller.code, params.slave_id, endpoint.describe(), params.read_cycle,
            len(parsed), len(poller.plan),
        )
        return True

    def _acquire(
        self, params: DriverModbusRtuParameter, endpoint: Endpoint,
        timing: LineTiming, poller: Poller,
    ) -> tuple[LineWorker, DtuSlot | None]:
        """Acquire the line (and the DTU slot in listen mode) and attach ``poller``;
        on any failure release what was acquired and re-raise."""
        slot: DtuSlot | None = None
        line: LineWorker | None = None
        try:
            if isinstance(endpoint, DtuEndpoint):
                slot = self.dtu_registry.acquire(port_settings(params), endpoint,
                                                 dtu_access(params))
                dtu_slot = slot
                line = self.registry.acquire(endpoint, timing, connector=lambda: dtu_slot)
                slot.attach(line)
            else:
                line = self.registry.acquire(endpoint, timing)
            poller.start(line)
        except BaseException:
            poller.stop()
            if line is not None:
                line.detach(poller)
                self.registry.release(line)
            if slot is not None:
                self.dtu_registry.release(slot)
            raise
        return line, slot

    def stop_device(self) -> bool:
        """Stop polling; pending writes of this device fail.  False if it was not running."""
        poller, line = self._poller, self._line
        if poller is None or line is None:
            return False
        poller.stop()
        line.detach(poller)
        self._line_stats = line.stats.as_dict()
        self._poller = self._line = None
        self._last_poller = poller
        self.registry.release(line)
        slot, self._slot = self._slot, None
        if slot is not None:
            self.dtu_registry.release(slot)
        self._status = DeviceDriverStatus.STOPPED
        self.logger.info("%s: stopped", poller.code)
        return True

    def update_addresses(self, addresses: Sequence[DeviceAddressItem],
                         actions: Sequence[DeviceAction] | None = None) -> None:
        """Replace the address list (and the actions, unless None) while running: re-plan
        on the worker between two reads.  New items start Unknown; removed ones are no
        longer read; unchanged ones keep their state.  ValueError if invalid."""
        if self._params is None:
            raise RuntimeError("update_addresses before start_device")
        parsed = validate_items(list(addresses), self._params)
        new_actions = self._actions if actions is None else list(actions)
        validate_actions(new_actions, parsed)  # an action's item may be gone
        if self._poller is not None:
            # a trial build of the specs, plan and decoders: a list the codec or the
            # planner refuses raises here and the device keeps its items and plan
            Poller(self._poller.sink, self._poller.code, self._params, parsed, self.logger)
            self._poller.replace_items(parsed).result()
        self._actions = new_actions

    # -- subscribers (poll/listeners.py) --------------------------------------------------
    def subscribe(self, listener: Listener[DriverModbusRtu]) -> None:
        """Add ``listener`` (an :class:`edgemodbus.Listener`) after those subscribed: it
        hears from the next delivery on, across restarts, until :meth:`unsubscribe`;
        ``addresses_updated_callback`` goes first.  Any thread.  ValueError when it is
        already subscribed or lacks a method."""
        self._subscribers.add(listener)

    def unsubscribe(self, listener: Listener[DriverModbusRtu]) -> None:
        """Remove ``listener`` (the others stay); a delivery under way on the line
        worker may still reach it.  Any thread.  ValueError when it is not subscribed."""
        self._subscribers.remove(listener)

    # -- status --------------------------------------------------------------------------
    @property
    def device_driver_status(self) -> DeviceDriverStatus:
        if self._poller is not None:
            return self._poller.status
        return self._status

    @property
    def is_enable(self) -> bool:
        return self._enabled

    @property
    def data_item_count(self) -> int:
        poller = self._poller or self._last_poller
        return len(poller.items) if poller is not None else 0

    @property
    def address_items(self) -> list[DeviceAddressItem]:
        """The items in force (after ``update_addresses`` too): the objects whose state
        the line worker stores (poll/store.py); [] before start."""
        poller = self._poller or self._last_poller
        return [state.item for state in poller.items] if poller is not None else []

    def read_plan(self) -> list[dict[str, Any]]:
        """The read blocks in force: area, start, count and the names of their items."""
        if self._poller is None:
            return []
        return [block_dict(b, self._poller.items) for b in self._poller.plan]

    def snapshot(self) -> dict[str, Any]:
        """The runtime snapshot (camelCase keys; each device's items read at one moment),
        values as held (NaN, bytes, datetime); ``codec.json_bytes`` writes it as JSON."""
        poller = self._poller or self._last_poller
        items = poller.store.snapshot() if poller is not None else {}  # at one moment
        params = self._params
        return {
            "deviceCode": self._code(self._org),
            "deviceDriverStatus": self.device_driver_status.value,
            "readCycle": params.read_cycle if params is not None else None,
            "dataItemCount": len(items),
            "items": items,
        }

    def stats(self) -> dict[str, Any]:
        """Counters of this device and of its line (camelCase keys)."""
        poller = self._poller or self._last_poller
        if poller is None:
            return {"deviceDriverStatus": self.device_driver_status.value}
        result = poller.counters.as_dict()
        line = self._line.stats.as_dict() if self._line is not None else self._line_stats
        result["reconnects"] = line.get("reconnects", 0)
        result["avgRoundTrip"] = line.get("avgRoundTrip", 0.0)
        result["line"] = line
        result["deviceDriverStatus"] = self.device_driver_status.value
        return result

    # -- writes --------------------------------------------------------------------------
    def write_address(self, name: str, value: Any) -> tuple[bool, str | None]:
        """Write one item; True only once the slave confirmed it."""
        return self.write_addresses([(name, value)])

    def write_addresses(self, items: Iterable[tuple[str, Any]]) -> tuple[bool, str | None]:
        """Write several items, merging contiguous registers (or coils) of one area into
        as few requests as possible.  (False, reasons) if any write failed."""
        line = self._line
        if line is not None and line.on_worker():
            return False, (
                "write_address(es) called on the line worker (from a callback) cannot wait "
                "for its own line: use write_address(es)_async, or write from another thread"
            )
        prepared = self._prepare_writes(items)
        if isinstance(prepared, str):
            return False, prepared
        return _wait_write(prepared)

    def submit_writes(self, items: Iterable[tuple[str, Any]]) -> Future[tuple[bool, str | None]]:
        """:meth:`write_addresses` without waiting (the gateway's Modbus TCP server): the
        future resolves to what it returns.  Raises at once, before anything is queued,
        ``ValueError`` for an unknown item or a value its codec refuses, and
        ``ModbusConnectionError`` when the device is not running.  Done-callbacks run on
        the line's worker: keep them short."""
        poller = self._running()
        return poller.submit_writes(plan_writes(poller.by_name, list(items)))

    def read_now(self, names: Sequence[str] | None = None) -> Future[dict[str, dict[str, Any]]]:
        """Read these items (None: all, on-demand ones too) now through the line's queue
        and report them (docs/reporting.md); the future: their snapshot entries by name.
        KeyError: an unknown item; ModbusConnectionError: the device is not running."""
        return self._running().submit_read(names)

    def publish_snapshot(self) -> Future[None]:
        """Publish the snapshot now (Pascal.Edge's ``PublishDeviceSnapshot()``) on the
        line worker, by the periodic snapshot's path (docs/reporting.md)."""
        return self._running().submit_snapshot()

    def _running(self) -> Poller:
        if self._poller is None:
            raise ModbusConnectionError(f"{self._code(self._org)}: device is not running")
        return self._poller

    async def write_address_async(self, name: str, value: Any) -> tuple[bool, str | None]:
        return await self.write_addresses_async([(name, value)])

    async def write_addresses_async(self, items: Iterable[tuple[str, Any]], exact: bool = False
                                    ) -> tuple[bool, str | None]:
        prepared = self._prepare_writes(items, exact)  # exact: poll/writes.py exact_problem
        if isinstance(prepared, str):
            return False, prepared
        import asyncio  # here: 25 ms of every start otherwise (`edgemodbus read`)
        try:
            return await asyncio.wrap_future(prepared)
        except Exception as exc:
            return False, str(exc)

    def _prepare_writes(self, items: Iterable[tuple[str, Any]],
                        exact: bool = False) -> Future[Any] | str:
        poller = self._poller
        if poller is None:
            return "device is not running"
        try:
            ops: list[WriteOp] = plan_writes(poller.by_name, list(items), exact)
        except ValueError as exc:
            return str(exc)
        return poller.submit_writes(ops)

    # -- actions (poll/actions.py) --------------------------------------------------------
    @property
    def actions(self) -> list[DeviceAction]:
        """The actions given to :meth:`start_device` (or the last update_addresses)."""
        return list(self._actions)

    def run_action(self, name: str,
                   params: Mapping[str, Any] | None = None) -> tuple[bool, str | None]:
        """Run the action ``name`` with ``params`` (parameter name -> value; missing ones
        take their defaults): everything is checked before a request is sent, then its
        requests go out in its function code; (True, None) once the slave confirmed all
        of them, else (False, why): the first failure stops the action."""
        line = self._line
        if line is not None and line.on_worker():
            return False, ("run_action called on the line worker (from a callback) cannot "
                           "wait for its own line: use run_action_async, or another thread")
        prepared = self._prepare_action(name, params)
        return (False, prepared) if isinstance(prepared, str) else _wait_write(prepared)

    async def run_action_async(self, name: str, params: Mapping[str, Any] | None = None
                               ) -> tuple[bool, str | None]:
        prepared = self._prepare_action(name, params)
        if isinstance(prepared, str):
            return False, prepared
        import asyncio  # here: 25 ms of every start otherwise (`edgemodbus read`)
        try:
            return await asyncio.wrap_future(prepared)
        except Exception as exc:
            return False, str(exc)

    def _prepare_action(self, name: str,
                        params: Mapping[str, Any] | None) -> Future[Any] | str:
        poller = self._poller
        if poller is None:
            return "device is not running"
        try:
            action = find_action(self._actions, name)
            ops = plan_action(action, params or {}, poller.by_name)
        except ValueError as exc:
            return str(exc)
        future = poller.submit_writes(ops, whole=True)
        return prefix_errors(future, f"action {name!r}: ")

    # -- gateway forward mode -------------------------------------------------------------
    def forward(self, pdu: bytes, timeout: float | None = None) -> Future[bytes]:
        """Send a request PDU (function code and data) to this device's slave through
        its line's queue, like a write (edgemodbus/line/forward.py); the future's
        result is the reply PDU: normal, or an exception reply passed through.

        Raises at once a :class:`~edgemodbus.protocol.forward.ForwardRequestError` for a
        PDU that is not forwarded (``exception_code`` 01 or 03), ``ValueError`` for a
        bad ``timeout`` (seconds; default the device's readTimeout).  The future fails
        with ``ModbusTimeoutError``, ``ProtocolError`` or ``ModbusConnectionError``
        (also when the device is not running): ``exception_code_for`` in
        :mod:`edgemodbus.protocol.forward` maps each to the code to answer.  A timeout
        fails the future after ``timeout``, before the line's settle.  Done-callbacks
        run on the line's worker: keep them short (hand over to an event loop)."""
        check_request(pdu)
        line, params = self._line, self._params
        if line is None or params is None or self._poller is None:
            failed: Future[bytes] = Future()
            failed.set_exception(ModbusConnectionError(
                f"{self._code(self._org)}: device is not running, nothing forwarded"))
            return failed
        wait = params.read_timeout / 1000 if timeout is None else timeout
        return line.forward(params.slave_id, pdu, wait)

    # -- helpers -------------------------------------------------------------------------
    def _code(self, org: DeviceOrganizationParameter | None) -> str:
        return _device_code(org, self._params)


class _Sink:
    """The driver as its poller sees it (a :class:`~edgemodbus.poll.sink.PollSink`): the
    host's callbacks and the subscribers, read at each delivery.  With no batch callback
    the head of the list is left out: no subscriber, no callback, no call at all."""

    __slots__ = ("source",)

    def __init__(self, driver: DriverModbusRtu) -> None:
        self.source = driver

    def item_callback(self) -> ItemCallback | None:
        return self.source.address_updated_callback

    def listeners(self) -> tuple[Listener[DriverModbusRtu], ...]:
        driver = self.source
        if driver.addresses_updated_callback is None:
            return driver._subscribers.listeners
        return driver._subscribers.with_head

    def snapshot_publisher(self) -> SnapshotPublisher | None:
        return self.source.snapshot_publisher

    def snapshot(self) -> dict[str, Any]:
        return self.source.snapshot()


def _device_code(
    org: DeviceOrganizationParameter | None, params: DriverModbusRtuParameter | None
) -> str:
    if org is not None and org.device_code:
        return str(org.device_code)
    return f"slave{params.slave_id}" if params is not None else "device"


def _timing(params: DriverModbusRtuParameter) -> LineTiming:
    return LineTiming(
        response_timeout=params.read_timeout / 1000,
        byte_timeout=params.byte_timeout / 1000,
        settle_timeout=None if params.settle_timeout is None else params.settle_timeout / 1000,
        connect_timeout=params.connect_timeout / 1000,
        reconnect_interval=params.reconnect_interval / 1000,
        max_backoff=params.max_backoff / 1000,
        request_interval=params.request_interval / 1000,
    )


def _wait_write(future: Future[Any]) -> tuple[bool, str | None]:
    try:
        result: tuple[bool, str | None] = future.result()
    except Exception as exc:
        return False, str(exc)
    return result


def port_settings(params: DriverModbusRtuParameter) -> PortSettings:
    """What a listen-mode device asks of its listen port (every device naming the port
    must agree; the allow-list normalised and sorted, so that the order it is listed in
    does not matter)."""
    return PortSettings(
        host=params.listen_host,
        port=params.effective_listen_port,
        registration=params.registration,
        pattern=params.registration_pattern,
        length=params.registration_length,
        timeout=params.registration_timeout / 1000,
        heartbeat=params.heartbeat_bytes,
        max_bytes=params.registration_max_bytes,
        byte_rate=params.registration_byte_rate,
        max_unregistered=params.max_unregistered,
        max_per_source=params.max_unregistered_per_source,
        allow_from=networks(params.listen_allow_from, "listenAllowFrom"),
        duplicate_id=params.duplicate_id,
        flip_limit=params.id_flip_limit, flip_window=params.id_flip_window / 1000,
        engine=None if params.engine == "auto" else params.engine,
        loop_threads=params.loop_threads)


def dtu_access(params: DriverModbusRtuParameter) -> DtuAccess:
    """Who may register as a listen-mode device's DTU (every device behind the DTU must
    agree): its source allow-list and registration key (bytes, as the packet is read)."""
    return DtuAccess(allow_from=networks(params.dtu_allow_from, "dtuAllowFrom"),
                     key=key_bytes(params.registration_key))
