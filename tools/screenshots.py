"""Screenshots of the web console's main pages for docs/console/ (docs/console.md).

Runs a gateway with its console (console/, 127.0.0.1, an ephemeral port) over a
pymodbus slave (tests/peers.py) with two devices, one with an action, and takes with
headless Chromium (Debian's chromium and chromium-driver, Selenium): the overview, a
device's tags live, a write confirmed, the device form with a field's error and the
read plan, and the login page.  ``python tools/screenshots.py [--out docs/console]``.
The descriptor's labels are Chinese (the seed's): install a CJK font for the browser
(Debian: fonts-wqy-zenhei) or they show as boxes.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from selenium.webdriver.common.by import By
from selenium.webdriver.support.ui import Select, WebDriverWait
from tests.browser.conftest import make_browser
from tests.console_gateway import console_gateway
from tests.peers import PymodbusSlave

from edgemodbus.console.auth import hash_password

WAIT = 30.0


def wait_text(browser: Any, css: str, want: str) -> None:
    script = "return [...document.querySelectorAll(arguments[0])].map((e) => e.innerText)"
    WebDriverWait(browser, WAIT).until(
        lambda b: any(want in t for t in b.execute_script(script, css)), f"{css}: {want}")


def field_at(browser: Any, path: str) -> list[Any]:
    """The device form's field of ``path`` (none yet while the form loads)."""
    return list(browser.find_elements(By.CSS_SELECTOR, f'[data-path="{path}"]'))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("docs/console"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp, PymodbusSlave("rtu-over-tcp",
                                                             units=(1, 2)) as slave:
        folder = Path(tmp) / "cfg"
        with console_gateway(folder, slave.port, tags=12, devices=2) as gateway:
            doc = json.loads((folder / "dev1.json").read_text())
            doc["addressList"][0].update(name="PumpSpeed", unit="rpm")
            doc["addressList"][1].update(name="Setpoint", deviceDataType="Int16",
                                         dataMultiplier=0.1, unit="bar")
            doc["addressList"].append({"name": "Pressure", "address": "ir:3",
                                       "deviceDataType": "UInt16", "unit": "kPa"})
            (folder / "dev1.json").write_text(json.dumps(doc))
            gateway.reload()
            assert gateway.console is not None
            url = gateway.console.url
            browser = make_browser(1400, 820)
            try:
                browser.get(url)
                wait_text(browser, 'tr[data-code="Dev2"] td.status', "Running")
                # a second overview sample (2 s later): the cycle rate is shown
                wait_text(browser, 'tr[data-code="Dev1"] td:nth-child(6)', ".")
                WebDriverWait(browser, WAIT).until(lambda b: b.execute_script(
                    "return Number(document.querySelector('tr[data-code=\"Dev1\"] "
                    "td:nth-child(6)').innerText) > 0"))
                browser.save_screenshot(str(args.out / "overview.png"))
                browser.get(url + "#/device/Dev1")
                wait_text(browser, 'tr[data-tag="PumpSpeed"] td.status', "Ok")
                slave.set_registers(1, "hr", 0, [1480])
                wait_text(browser, 'tr[data-tag="PumpSpeed"] td.value', "1480")
                browser.find_element(By.CSS_SELECTOR,
                                     'button.write[data-tag="Setpoint"]').click()
                field = browser.find_element(By.ID, "write-value")
                field.clear()
                field.send_keys("4.5")
                browser.find_element(By.ID, "write-send").click()
                wait_text(browser, "#write-outcome", "confirmed")
                browser.save_screenshot(str(args.out / "device.png"))
                browser.get(url + "#/commission")
                WebDriverWait(browser, WAIT).until(lambda b: field_at(b, "organization.deviceCode"))
                field_at(browser, "organization.deviceCode")[0].send_keys("Boiler3")
                Select(field_at(browser, "communication.baudRate")[0]).select_by_value("19200")
                sid = field_at(browser, "communication.slaveId")[0]
                sid.clear()
                sid.send_keys("300")
                browser.find_element(By.ID, "check").click()
                wait_text(browser, '[data-field="communication.slaveId"] .field-error', "255")
                browser.save_screenshot(str(args.out / "commission-error.png"))
                sid.clear()
                sid.send_keys("7")
                browser.find_element(By.ID, "add-item").click()
                browser.find_element(By.ID, "check").click()
                wait_text(browser, "#plan", "requests per cycle")
                browser.execute_script("window.scrollTo(0, document.body.scrollHeight)")
                browser.save_screenshot(str(args.out / "commission-plan.png"))
            finally:
                browser.quit()
        users = {"users": [{"name": "ops", "passwordHash": hash_password("x")}]}
        with console_gateway(Path(tmp) / "cfg2", slave.port, users) as gateway:
            assert gateway.console is not None
            browser = make_browser(900, 500)
            try:
                browser.get(gateway.console.url)
                WebDriverWait(browser, WAIT).until(lambda b: b.find_elements(By.ID, "login-user"))
                browser.save_screenshot(str(args.out / "login.png"))
            finally:
                browser.quit()
    for name in sorted(args.out.glob("*.png")):
        print(name)
    return 0


if __name__ == "__main__":
    sys.exit(main())
