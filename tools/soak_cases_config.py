"""Cases of `make soak-gateway` that end at start: a gateway folder with a hostile value
(issue #25's config row, and the Sparkplug bdSeq file that is not ours) must give exit
status 2 and one short line naming the field, not a log of megabytes or a traceback;
a file the gateway was told to write and did not make is left as it was."""

from __future__ import annotations

import os
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

from tests.gateway_proc import GatewayProcess, device_file, write_json
from tools.soak_gw_base import MAX_LINE

START_S = 60.0  # a hostile file must be refused within this
MAX_START_LINES = 3


@dataclass(frozen=True)
class StartCase:
    """A folder (``files`` writes it) the gateway must refuse: exit ``expect_exit``,
    at most MAX_START_LINES lines, one of them matching ``expect``; ``untouched``
    names files that must hold the same bytes after."""

    name: str
    row: str
    files: Callable[[Path], None]
    expect: str
    expect_exit: int = 2
    untouched: tuple[str, ...] = ()


def gateway_with(**keys: Any) -> Callable[[Path], None]:
    """A folder of one device (polling no one: the gateway must stop before it) and a
    gateway file with ``keys``."""
    def files(conf: Path) -> None:
        write_json(conf / "dev1.json", device_file(9, 1, "dev1"))
        write_json(conf / "gateway.json", keys)
    return files


def unknown_keys(conf: Path) -> None:
    gateway_with()(conf)
    extra = {f"k{i}": i for i in range(200_000)}
    write_json(conf / "gateway.json", {"metrics": {"port": 0}, **extra})


def fifo_spool(conf: Path) -> None:
    os.mkfifo(conf / "spool.db")
    gateway_with(mqtt={"port": 9, "storeAndForward": {"path": "spool.db"}})(conf)


FOREIGN_BDSEQ = '{"gatewayId": "gw", "metrics": {"port": 9108}}\n'


def foreign_bdseq(conf: Path) -> None:
    (conf / "other.json").write_text(FOREIGN_BDSEQ)
    gateway_with(mqtt={"port": 9, "mode": "sparkplug", "sparkplug": {
        "groupId": "G", "edgeNodeId": "n1", "bdSeqFile": "other.json"}})(conf)


def start_cases() -> list[StartCase]:
    huge = "g" * 10_000_000
    return [
        StartCase("config-huge-id", "config: a 10 MB gatewayId",
                  gateway_with(gatewayId=huge), r"gatewayId"),
        StartCase("config-huge-host", "config: a 10 MB mqtt.host",
                  gateway_with(mqtt={"host": huge}), r"mqtt\.host"),
        StartCase("config-unknown-keys", "config: 200,000 unknown keys", unknown_keys,
                  r"gateway .* running", expect_exit=0),
        StartCase("config-fifo-spool", "config: a FIFO as the spool's path", fifo_spool,
                  r"storeAndForward\.path"),
        StartCase("config-tiny-timeout", "config: serve.idleTimeoutS 1e-12",
                  gateway_with(serve={"listen": "127.0.0.1:1", "idleTimeoutS": 1e-12}),
                  r"idleTimeoutS"),
        StartCase("sparkplug-foreign-bdseq",
                  "Sparkplug: bdSeqFile names an existing file that is not a bdSeq",
                  foreign_bdseq, r"bdSeqFile", untouched=("other.json",)),
    ]


def run_start_case(case: StartCase, workdir: Path) -> dict[str, Any]:
    """Start the gateway on the case's folder and look at how it ends."""
    conf = workdir / case.name
    conf.mkdir()
    case.files(conf)
    before = {name: (conf / name).read_bytes() for name in case.untouched}
    log_path = workdir / f"{case.name}.log"
    rss = 0
    started = time.monotonic()
    with GatewayProcess(conf, log_path) as gw:
        while gw.alive() and time.monotonic() - started < START_S:
            if case.expect_exit == 0 and re.search(case.expect, gw.log):
                break  # it runs, having said what it ignored
            try:
                rss = max(rss, gw.usage().rss_kib)
            except OSError:
                break
            time.sleep(0.1)
        rc = gw.stop() if gw.alive() else gw.wait()
        seconds = time.monotonic() - started
        text = gw.log
    lines = text.splitlines()
    found = [ln for ln in lines if re.search(case.expect, ln)]
    bad = []
    if rc != case.expect_exit:
        bad.append(f"exit status {rc}, not {case.expect_exit}")
    if len(lines) > MAX_START_LINES and case.expect_exit != 0:
        bad.append(f"{len(lines)} log lines")
    if case.expect_exit == 0 and len(lines) > 30:
        bad.append(f"{len(lines)} log lines")
    if any(len(ln) > MAX_LINE for ln in lines):
        bad.append(f"a log line of {max(len(ln) for ln in lines)} characters")
    if "Traceback" in text:
        bad.append("a traceback")
    if not found:
        bad.append(f"no line /{case.expect}/")
    for name, data in before.items():
        if (conf / name).read_bytes() != data:
            bad.append(f"{name} was changed")
    return {"case": case.name, "row": case.row, "exit": rc, "seconds": round(seconds, 2),
            "rssKiB": rss, "logLines": len(lines),
            "longestLine": max((len(ln) for ln in lines), default=0),
            "logBytes": len(text.encode()), "line": (found or lines or [""])[0][:160],
            "failures": bad}
