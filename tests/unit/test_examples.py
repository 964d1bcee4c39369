"""The shipped examples load as they are (validated, nothing connected), cover every
transport and northbound mode, and the systemd unit's paths agree with them and with the
README's: the config folder /etc/edgemodbus, the venv /opt/edgemodbus/venv, and the state
folder /var/lib/edgemodbus (``StateDirectory=``) that holds every file the gateway writes
(the spool, the Sparkplug bdSeq file)."""

from __future__ import annotations

import json
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

import edgemodbus as em
from edgemodbus.gateway import GatewayConfig, load_gateway_config
from edgemodbus.serve.settings import unknown_devices

TOP = Path(__file__).resolve().parents[2]
EXAMPLES = TOP / "examples"
UNIT = EXAMPLES / "edgemodbus.service"
DEVICE_FILES = sorted(p for p in EXAMPLES.glob("*.json") if p.name != "gateway.json")
GATEWAY_FOLDERS = sorted(p for p in EXAMPLES.iterdir() if p.is_dir())


def unit_settings(text: str) -> dict[str, list[str]]:
    """Key -> values of a systemd unit (keys may repeat; sections are not kept apart:
    no key of ours is in two of them)."""
    settings: dict[str, list[str]] = {}
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";", "[")):
            continue
        key, sep, value = line.partition("=")
        assert sep, f"{UNIT.name}: not a key=value line: {raw!r}"
        settings.setdefault(key.strip(), []).append(value.strip())
    return settings


UNIT_SETTINGS = unit_settings(UNIT.read_text(encoding="utf-8"))
#: /var/lib/<StateDirectory=> ("StateDirectory=" missing: a path no example uses)
STATE_DIR = Path("/var/lib") / UNIT_SETTINGS.get("StateDirectory", ["(no StateDirectory=)"])[0]
EXEC = shlex.split(UNIT_SETTINGS["ExecStart"][0])
CONFIG_DIR = EXEC[EXEC.index("--config-dir") + 1]


@pytest.mark.parametrize("path", DEVICE_FILES, ids=lambda p: p.name)
def test_each_device_file_loads(path: Path) -> None:
    cfg = em.load_device_config(path)
    assert cfg.address_list, f"{path.name}: no items"


@pytest.mark.parametrize("page", ["README.md", "docs/device-files.md"])
def test_the_worked_device_file_is_the_example(page: str) -> None:
    """The device file a page shows is examples/rtu-over-tcp.json, key for key."""
    text = (TOP / page).read_text(encoding="utf-8")
    shown = json.loads(text.split("```json\n", 1)[1].split("```", 1)[0])
    assert shown == json.loads((EXAMPLES / "rtu-over-tcp.json").read_text(encoding="utf-8"))


def test_every_transport_has_its_device_file() -> None:
    transports = {em.load_device_config(p).communication.transport for p in DEVICE_FILES}
    assert transports >= {"rtu", "rtu-over-tcp", "tcp", "rtu-over-tcp-server"}


def load_folder(folder: Path, tmp: Path) -> tuple[GatewayConfig, list[em.DeviceConfig]]:
    """The folder's gateway file and device files, loaded as the gateway loads them,
    with the unit's state folder standing at ``tmp`` (nothing is written there)."""
    state = tmp / "state"
    state.mkdir()
    text = (folder / "gateway.json").read_text(encoding="utf-8")
    copy = tmp / "gateway.json"
    copy.write_text(text.replace(f"{STATE_DIR}/", f"{state}/"), encoding="utf-8")
    devices = [em.load_device_config(p) for p in sorted(folder.glob("*.json"))
               if p.name != "gateway.json"]
    return load_gateway_config(copy), devices


def written_paths(data: dict[str, Any]) -> list[str]:
    """The files a gateway file makes the gateway write: the spool and the bdSeq file."""
    mqtt = data.get("mqtt") or {}
    paths = [(mqtt.get("storeAndForward") or {}).get("path"),
             (mqtt.get("sparkplug") or {}).get("bdSeqFile")]
    return [p for p in paths if p]


@pytest.mark.parametrize("folder", GATEWAY_FOLDERS, ids=lambda p: p.name)
def test_each_gateway_folder_loads(folder: Path, tmp_path: Path) -> None:
    cfg, devices = load_folder(folder, tmp_path)
    assert devices, f"{folder.name}: no device file"
    codes = [d.organization.device_code for d in devices]
    assert all(codes) and len(set(codes)) == len(codes)
    if cfg.serve is not None:
        assert unknown_devices(cfg.serve, [c for c in codes if c]) == []


def test_every_northbound_mode_has_its_folder(tmp_path: Path) -> None:
    modes = set()
    for n, folder in enumerate(GATEWAY_FOLDERS):
        (tmp_path / str(n)).mkdir()
        cfg, _ = load_folder(folder, tmp_path / str(n))
        if cfg.mqtt is not None:
            modes.add(cfg.mqtt.mode)
        if cfg.serve is not None:
            modes.add("serve")
    assert modes == {"per-item", "batch", "sparkplug", "serve"}


def test_the_files_the_gateway_writes_are_in_the_units_state_folder() -> None:
    """Under the unit, only StateDirectory= is writable (ProtectSystem=strict): every
    spool and bdSeq path of the examples is there, and the state folder is what the
    gateway's default bdSeq file uses ($STATE_DIRECTORY)."""
    found = {p for path in [EXAMPLES / "gateway.json", *EXAMPLES.glob("*/gateway.json")]
             for p in written_paths(json.loads(path.read_text(encoding="utf-8")))}
    assert found == {f"{STATE_DIR}/spool.db", f"{STATE_DIR}/sparkplug.bdseq"}
    assert UNIT_SETTINGS.get("StateDirectory") == ["edgemodbus"], "the unit needs a state folder"
    assert UNIT_SETTINGS["ProtectSystem"] == ["strict"]


def test_the_unit_runs_the_gateway_from_the_readmes_paths() -> None:
    readme = (TOP / "README.md").read_text(encoding="utf-8")
    assert EXEC[1:4] == ["-m", "edgemodbus.gateway", "--config-dir"]
    venv = str(Path(EXEC[0]).parents[1])
    assert venv == "/opt/edgemodbus/venv" and f"python3 -m venv {venv}" in readme
    assert CONFIG_DIR == "/etc/edgemodbus" and f"`{CONFIG_DIR}`" in readme
    assert str(STATE_DIR) in readme
    assert UNIT_SETTINGS["ReadOnlyPaths"] == [CONFIG_DIR]
    assert UNIT_SETTINGS["ExecReload"] == ["/bin/kill -HUP $MAINPID"]  # SIGHUP reloads


def test_systemd_analyze_verifies_the_unit(tmp_path: Path) -> None:
    """``systemd-analyze verify`` on the unit, with ExecStart's interpreter replaced by
    this one (the unit's venv does not exist here; verify checks that it is executable)."""
    tool = shutil.which("systemd-analyze")
    if tool is None:
        pytest.skip("systemd-analyze is not installed (Debian package systemd)")
    text = UNIT.read_text(encoding="utf-8").replace(EXEC[0], sys.executable)
    copy = tmp_path / UNIT.name
    copy.write_text(text, encoding="utf-8")
    out = subprocess.run([tool, "verify", str(copy)], capture_output=True, text=True,
                         timeout=60, check=False)
    assert out.returncode == 0 and out.stderr.strip() == "", out.stderr
