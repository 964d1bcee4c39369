"""Start-up cost (issue 29): ``import edgemodbus`` loads no pydantic model, driver, codec
or C extension, and ``edgemodbus read`` none of the gateway, the simulator, scan, rich,
sqlite3 or asyncio; the public names still import as before."""

from __future__ import annotations

import subprocess
import sys

import edgemodbus


def _modules_after(code: str) -> set[str]:
    """The modules loaded by ``code`` in a fresh interpreter."""
    probe = f"{code}\nimport sys\nprint('\\n'.join(sorted(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                         timeout=120, check=True)
    return set(out.stdout.split())


def test_every_public_name_imports() -> None:
    for name in edgemodbus.__all__:
        assert getattr(edgemodbus, name) is not None, name
    assert set(edgemodbus.__all__) <= set(dir(edgemodbus))
    from edgemodbus import DriverModbusRtu, load_device_config

    assert DriverModbusRtu.__module__ == "edgemodbus.driver"
    assert load_device_config.__module__ == "edgemodbus.config.device"


def test_an_unknown_name_is_an_attribute_error() -> None:
    try:
        edgemodbus.NoSuchName  # type: ignore[attr-defined]  # noqa: B018
    except AttributeError as exc:
        assert "NoSuchName" in str(exc)
    else:
        raise AssertionError("edgemodbus.NoSuchName did not raise")


def test_import_edgemodbus_loads_nothing_heavy() -> None:
    loaded = _modules_after("import edgemodbus")
    heavy = {"pydantic", "edgemodbus.config", "edgemodbus.driver", "edgemodbus._native",
             "edgemodbus._ffi", "edgemodbus.codec", "asyncio"}
    assert not heavy & loaded, sorted(heavy & loaded)


def test_the_read_path_loads_no_service() -> None:
    loaded = _modules_after(
        "from edgemodbus.cli import build_parser\n"
        "args = build_parser('read').parse_args(['read', '--host', '127.0.0.1', 'hr:0'])\n"
        "import edgemodbus.cli.polling\n"
        "assert args.func is not None")
    assert "edgemodbus.driver" in loaded  # the read path itself is there
    unwanted = {"edgemodbus.gateway", "edgemodbus.sim", "edgemodbus.commission",
                "edgemodbus.northbound", "edgemodbus.serve", "rich", "sqlite3", "asyncio"}
    assert not unwanted & loaded, sorted(unwanted & loaded)
