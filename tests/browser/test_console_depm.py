"""The console on the emulated dual-EPM rig, in headless Chromium: no camera, a sketch of both
arms from their measured joints (checked against the rig's kinematics on the emulator's own
joint angles), and E-STOP brings both arms to rest (the emulated arms' joint speeds)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rigctl.apps.testing import wait_for
from rigctl.core.config import load_rig
from rigctl.physics.kinematics import ArmKinematics, base_transform
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
    yield from bench_daemon("depm", tmp_path_factory)


def moving(truth: dict) -> bool:
    return any(max(abs(v) for v in arm["qd"]) > 1e-3 for arm in truth["arms"].values())


def test_the_arms_page_and_estop(rig, browser, screenshots):
    daemon, backdoor = rig
    depm = load_rig(daemon.rig_path).depm
    driver = open_console(browser, daemon)
    assert js(driver, "document.getElementById('camera').hidden")
    assert not js(driver, "document.getElementById('arms').hidden")
    driver.find_element("css selector", "#plan-choice option[value='depm-plan.json']").click()
    click(driver, "load-choice")
    wait_page(driver, "!document.getElementById('execute').disabled", 120.0, "the plan loaded")
    click(driver, "execute")
    wait_for(lambda: moving(backdoor.request("truth")), 60.0, "the arms moving")
    assert js(driver, "document.getElementById('plot-field').hidden")  # no coil field streamed
    # at rest, so the sketch and the emulator's joints describe the same pose: pause now
    click(driver, "pause-now")
    wait_page(driver, "rigctlConsole.state === 'paused'", 30.0, "paused")
    wait_for(lambda: not moving(backdoor.request("truth")), 10.0, "the arms at rest")
    truth = backdoor.request("truth")["arms"]
    wait_page(driver, "rigctlConsole.arms", 10.0, "the arms sketch drawn")
    sketch = js(driver, "rigctlConsole.arms")
    assert sketch["keep_out_mm"] == depm.keep_out_radius_mm
    for name, position, rpy, arm in zip(depm.arm_names, depm.arm_positions_mm, depm.arm_rpy_deg,
                                        sketch["arms"]):
        assert arm["name"] == name
        # the EPM centre from the emulator's joints, through the kinematics the arm's own model
        # gives; the sketch drew it from the measured joints the daemon streamed
        kinematics = ArmKinematics(base=base_transform(np.asarray(position) * 1e-3, rpy))
        epm_mm = kinematics.epm_pose(np.asarray(truth[name]["q"]))[0] * 1e3
        assert math.dist(arm["points_mm"][8], epm_mm) < 2.0, (arm["points_mm"][8], epm_mm)
        assert math.dist(arm["points_mm"][0], position) < 1e-6 + 0.1
    assert no_horizontal_scroll(driver)
    screenshots(driver, "depm-paused", full_page=True)
    click(driver, "resume")
    wait_page(driver, "rigctlConsole.state === 'running'", 30.0, "running again")
    wait_for(lambda: moving(backdoor.request("truth")), 30.0, "the arms moving again")
    click(driver, "estop")
    wait_for(lambda: not moving(backdoor.request("truth")), 5.0, "both arms at rest")
    wait_page(driver, "rigctlConsole.state === 'estopped'", 10.0, "the page says estopped")
