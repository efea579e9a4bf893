"""The console on the emulated coil board, in headless Chromium: the page fits a tablet, draws
the camera with the particles the tracker found, and its E-STOP zeroes the board's outputs (the
SyRen values on the emulated board's wire, read from its backdoor)."""

from __future__ import annotations

import math

import pytest

from rigctl.apps.testing import wait_for
from tests.browser.pages import (
    bench_daemon,
    click,
    js,
    no_horizontal_scroll,
    open_console,
    wait_page,
)

TRACKER_ERROR_MM = 0.5  # a particle's radius (1 mm spheres, seed 004)


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
    wait_for(lambda: driving(backdoor), 60.0, "the board driving its coils")
    assert no_horizontal_scroll(driver)
    screenshots(driver, "coil-board-running", full_page=True)
    # paused now, the particles come to rest: what the page drew against the emulator's truth
    click(driver, "pause-now")
    wait_page(driver, "rigctlConsole.state === 'paused'", 30.0, "paused")
    wait_for(lambda: not driving(backdoor), 10.0, "the coils off while paused")
    previous = backdoor.request("truth")["agents"]

    def at_rest() -> bool:
        now = backdoor.request("truth")["agents"]
        still = all(math.dist(a, b) < 1e-3 for a, b in zip(now, previous))
        previous[:] = now
        return still

    wait_for(at_rest, 10.0, "the particles at rest")
    seen = js(driver, "rigctlConsole.lastFrame.frame")
    drawn = wait_page(driver, f"rigctlConsole.lastFrame.frame > {seen + 2} && "
                      "rigctlConsole.lastFrame", 10.0, "frames of the particles at rest")
    truth = backdoor.request("truth")["agents"]
    assert len(drawn["positions_mm"]) == len(truth)
    for tracked, real in zip(drawn["positions_mm"], truth):
        assert math.dist(tracked, real) < TRACKER_ERROR_MM, (drawn["positions_mm"], truth)
    screenshots(driver, "coil-board-paused")
    click(driver, "resume")
    wait_page(driver, "rigctlConsole.state === 'running'", 30.0, "running again")
    wait_for(lambda: driving(backdoor), 30.0, "the board driving its coils again")
    click(driver, "estop")
    wait_for(lambda: not driving(backdoor), 5.0, "every SyRen output at zero")
    wait_page(driver, "rigctlConsole.state === 'estopped'", 10.0, "the page says estopped")
    wait_page(driver, "!document.getElementById('reset').disabled", 30.0, "reset enabled")
    click(driver, "reset")
    wait_page(driver, "rigctlConsole.state === 'idle'", 30.0, "idle again")
