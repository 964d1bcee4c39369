"""Headless Chromium from Debian (``chromium``, ``chromium-driver``: `make deps` installs
them) driven by Selenium.  The tests skip only when the browser is genuinely absent;
each test's driver quits in the fixture's finalizer (no chromium left behind)."""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from pathlib import Path

import pytest

CHROMIUM = next((p for p in (shutil.which("chromium"), "/usr/bin/chromium") if p and
                 Path(p).exists()), None)
CHROMEDRIVER = next((p for p in (shutil.which("chromedriver"), "/usr/bin/chromedriver")
                     if p and Path(p).exists()), None)


def make_browser(width: int = 1400, height: int = 900) -> object:
    """A headless Chromium under Selenium (Debian's binaries, no download)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--disable-extensions", "--no-first-run", f"--window-size={width},{height}"):
        options.add_argument(arg)
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)


@pytest.fixture
def browser() -> Iterator[object]:
    if CHROMIUM is None or CHROMEDRIVER is None:
        pytest.skip("chromium and chromium-driver (Debian) are not installed: make deps")
    pytest.importorskip("selenium")
    driver = make_browser()
    try:
        yield driver
    finally:
        driver.quit()  # type: ignore[attr-defined]
