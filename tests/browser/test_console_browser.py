"""The web console in a real browser (headless Chromium, Selenium): pages open, a value
changes live, a write reaches the slave, a bad form value shows its field's error, a
saved device is polled, a login is asked for when users are configured, and a device of
10,000 tags pages and filters."""

from __future__ import annotations

import json
from pathlib import Path

from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webdriver import WebDriver
from selenium.webdriver.support.ui import Select, WebDriverWait

from edgemodbus.console.auth import hash_password
from edgemodbus.gateway import Gateway
from tests.conftest import SlaveFactory
from tests.console_gateway import console_gateway
from tests.peers import default_register

WAIT = 30.0  # seconds: a loaded 2-core machine


def url(gateway: Gateway, page: str = "") -> str:
    assert gateway.console is not None
    return gateway.console.url + page


def texts(browser: WebDriver, css: str) -> list[str]:
    """The texts of the elements at ``css`` now (read in the page: the tables are
    re-rendered as values arrive, so element handles go stale)."""
    found = browser.execute_script(
        "return [...document.querySelectorAll(arguments[0])].map((e) => e.innerText)", css)
    return [str(t) for t in found]


def text_of(browser: WebDriver, css: str, want: str) -> str:
    """Wait until an element at ``css`` holds ``want``; its text."""
    WebDriverWait(browser, WAIT).until(
        lambda b: any(want in t for t in texts(b, css)),
        f"{css} holding {want!r}: {texts(browser, css)[:3]}")
    return next(t for t in texts(browser, css) if want in t)


def click(browser: WebDriver, by: str, what: str) -> None:
    """Click the element, found again if a re-render replaced it meanwhile."""
    def attempt(b: WebDriver) -> bool:
        try:
            b.find_element(by, what).click()
        except (StaleElementReferenceException, NoSuchElementException):
            return False
        return True
    WebDriverWait(browser, WAIT).until(attempt, f"{what} clickable")


def test_overview_and_a_value_changing_live(tmp_path: Path, slave_factory: SlaveFactory,
                                            browser: WebDriver) -> None:
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port) as gateway:
        browser.get(url(gateway))
        text_of(browser, 'tr[data-code="Dev1"] td.status', "Running")
        click(browser, By.LINK_TEXT, "Dev1")
        first = str(default_register(1, "hr", 3))
        text_of(browser, 'tr[data-tag="t3"] td.value', first)
        slave.set_registers(1, "hr", 3, [31337])
        text_of(browser, 'tr[data-tag="t3"] td.value', "31337")  # by the event stream
        assert texts(browser, 'tr[data-tag="t3"] td:nth-child(5)') == ["Ok"]


def test_write_a_tag_and_the_slave_changes(tmp_path: Path, slave_factory: SlaveFactory,
                                           browser: WebDriver) -> None:
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port) as gateway:
        browser.get(url(gateway, "#/device/Dev1"))
        text_of(browser, 'tr[data-tag="t1"] td.status', "Ok")
        click(browser, By.CSS_SELECTOR, 'button.write[data-tag="t1"]')
        field = browser.find_element(By.ID, "write-value")
        field.clear()
        field.send_keys("555")
        browser.find_element(By.ID, "write-send").click()
        text_of(browser, "#write-outcome", "confirmed by the slave")
        assert slave.registers(1, "hr", 1, 1) == [555]
        text_of(browser, 'tr[data-tag="t1"] td.value', "555")


def fill(browser: WebDriver, path: str, value: str) -> None:
    """Set a form field (waiting until the form shows it)."""
    css = f'[data-path="{path}"]'
    WebDriverWait(browser, WAIT).until(
        lambda b: any(e.is_displayed() for e in b.find_elements(By.CSS_SELECTOR, css)),
        f"form field {path} shown")
    field = browser.find_element(By.CSS_SELECTOR, css)
    if field.tag_name == "select":
        Select(field).select_by_value(value)
    else:
        field.clear()
        field.send_keys(value)


def test_bad_form_value_shows_the_field_error(tmp_path: Path, slave_factory: SlaveFactory,
                                              browser: WebDriver) -> None:
    slave = slave_factory("rtu-over-tcp")
    with console_gateway(tmp_path / "cfg", slave.port) as gateway:
        browser.get(url(gateway, "#/commission"))
        fill(browser, "communication.slaveId", "300")
        browser.find_element(By.ID, "check").click()
        error = text_of(browser, '[data-field="communication.slaveId"] .field-error', "300")
        assert "255" in error
        fill(browser, "communication.slaveId", "2")
        fill(browser, "addressList[0].address", "hr:zz")
        browser.find_element(By.ID, "check").click()
        text_of(browser, '[data-field="addressList[0].address"] .field-error', "zz")
        assert not (tmp_path / "cfg" / "new-device.json").exists()


def test_save_a_device_and_see_it_polled(tmp_path: Path, slave_factory: SlaveFactory,
                                         browser: WebDriver) -> None:
    slave = slave_factory("rtu-over-tcp")
    folder = tmp_path / "cfg"
    with console_gateway(folder, slave.port) as gateway:
        browser.get(url(gateway, "#/commission"))
        fill(browser, "organization.deviceCode", "Pump7")
        fill(browser, "communication.useTcp", "true")
        fill(browser, "communication.transport", "rtu-over-tcp")
        fill(browser, "communication.tcpHost", "127.0.0.1")
        fill(browser, "communication.tcpPort", str(slave.port))
        fill(browser, "communication.slaveId", "2")
        fill(browser, "addressList[0].name", "speed")
        fill(browser, "addressList[0].address", "hr:4")
        browser.find_element(By.ID, "check").click()
        text_of(browser, "#plan", "FC03 hr:4-4 (1)")
        fill(browser, "communication.readCycle", "200")
        browser.find_element(By.ID, "file-name").clear()
        browser.find_element(By.ID, "file-name").send_keys("pump7.json")
        browser.find_element(By.ID, "save").click()
        text_of(browser, "#save-result", "saved pump7.json")
        saved = json.loads((folder / "pump7.json").read_text())
        assert saved["communication"]["tcpPort"] == slave.port
        browser.find_element(By.ID, "saved-device").click()
        text_of(browser, "#device-status", "Running")
        text_of(browser, 'tr[data-tag="speed"] td.value', str(default_register(2, "hr", 4)))


def test_login_when_users_are_configured(tmp_path: Path, slave_factory: SlaveFactory,
                                         browser: WebDriver) -> None:
    slave = slave_factory("rtu-over-tcp")
    users = {"users": [{"name": "ops", "passwordHash": hash_password("pw-1", log2_n=4)}]}
    with console_gateway(tmp_path / "cfg", slave.port, users) as gateway:
        browser.get(url(gateway))
        browser.find_element(By.ID, "login-user").send_keys("ops")
        browser.find_element(By.ID, "login-password").send_keys("wrong")
        browser.find_element(By.ID, "login-submit").click()
        text_of(browser, "#login-result", "wrong user name")
        browser.find_element(By.ID, "login-password").clear()
        browser.find_element(By.ID, "login-password").send_keys("pw-1")
        browser.find_element(By.ID, "login-submit").click()
        text_of(browser, 'tr[data-code="Dev1"] td.status', "Running")
        text_of(browser, "#who", "logged in as ops")


def test_ten_thousand_tags_page_and_filter(tmp_path: Path, slave_factory: SlaveFactory,
                                           browser: WebDriver) -> None:
    slave = slave_factory("rtu-over-tcp", size=10_000)
    with console_gateway(tmp_path / "cfg", slave.port, tags=10_000, read_cycle=2000) as gateway:
        browser.get(url(gateway, "#/device/Dev1"))
        text_of(browser, "#pager", "page 1 of 100 (10000 tags)")
        assert len(browser.find_elements(By.CSS_SELECTOR, "#tags tr")) == 100
        browser.find_element(By.ID, "tag-filter").send_keys("t9999")
        text_of(browser, "#pager", "(1 tags)")
        text_of(browser, 'tr[data-tag="t9999"] td.value', str(default_register(1, "hr", 9999)))
        Select(browser.find_element(By.ID, "tag-status")).select_by_value("Invalid")
        text_of(browser, "#pager", "(0 tags)")


def test_run_an_action(tmp_path: Path, slave_factory: SlaveFactory, browser: WebDriver) -> None:
    slave = slave_factory("rtu-over-tcp")
    actions = [{"name": "preset", "functionCode": 16, "parameters": [
        {"name": "a", "item": "t1", "type": "UInt16"}, {"name": "b", "item": "t2"}]}]
    with console_gateway(tmp_path / "cfg", slave.port, extra={"actions": actions}) as gateway:
        browser.get(url(gateway, "#/device/Dev1"))
        text_of(browser, "#actions button", "Run preset")
        browser.find_element(By.CSS_SELECTOR, 'input[data-action="preset"]').send_keys(
            '{"a": 11, "b": 22}')
        click(browser, By.CSS_SELECTOR, "#actions button")
        text_of(browser, "#write-outcome", "action preset: confirmed by the slave")
        assert slave.registers(1, "hr", 1, 2) == [11, 22]
