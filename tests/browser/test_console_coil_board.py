"""The console on the emulated coil board, in headless Chromium: the page fits a tablet, draws
the camera with the particles the tracker found, and its E-STOP zeroes the board's outputs (the
SyRen values on the emulated board's wire, read from its backdoor)."""

from __future__ import annotations

import pytest

from rigctl.testing import wait_for
from tests.browser.pages import (
    bench_daemon,
    click,
    js,
    no_horizontal_scroll,
    open_console,
    wait_page,
)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    yield from bench_daemon("coil-board", tmp_path_factory)


def driving(backdoor) -> bool:
    return any(v != 0 for v in backdoor.request("truth")["outputs"])


def test_the_board_page_its_camera_and_estop(rig, browser, screenshots):
    daemon, backdoor = rig
    driver = open_console(browser, daemon, width=1024, height=768)
    assert js(driver, "rigctlConsole.hello.rig.kind") == "coil-board"
    units = js(driver, "rigctlConsole.hello.rig.channels.map(c => c.unit)")
    assert units and set(units) == {"drive"}
    driver.find_element("css selector", "#plan-choice option[value='coilboard-disk.json']").click()
    click(driver, "load-choice")
    wait_page(driver, "!document.getElementById('execute').disabled", 60.0, "the plan loaded")
    click(driver, "execute")
    first = wait_page(driver, "rigctlConsole.lastFrame", 60.0, "a camera frame drawn")
    wait_page(driver, f"rigctlConsole.lastFrame.frame > {first['frame'] + 3}", 20.0,
              "newer frames drawn")
    truth = backdoor.request("truth")
    assert len(js(driver, "rigctlConsole.lastFrame.positions_mm")) == len(truth["agents"])
    wait_for(lambda: driving(backdoor), 60.0, "the board driving its coils")
    assert no_horizontal_scroll(driver)
    screenshots(driver, "coil-board-running")
    click(driver, "estop")
    wait_for(lambda: not driving(backdoor), 5.0, "every SyRen output at zero")
    wait_page(driver, "rigctlConsole.state === 'estopped'", 10.0, "the page says estopped")
    wait_page(driver, "!document.getElementById('reset').disabled", 30.0, "reset enabled")
    click(driver, "reset")
    wait_page(driver, "rigctlConsole.state === 'idle'", 30.0, "idle again")
