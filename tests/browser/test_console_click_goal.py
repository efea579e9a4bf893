"""Click a goal on the console (issue 39 item 2), in headless Chromium against `rigctl daemon
--console` on the emulated six-coil bench: after a short run the page shows where the daemon last
saw the magnets; a click on each magnet and on its goal (real pointer clicks on the camera view)
gets a plan whose paths are drawn (an SVG the test reads), "execute goals" runs it, and the run
ends reached, with every magnet within the plan's tolerance of its clicked goal by the bench's
ground truth; a goal clicked in the wrong place is dragged to the right one first. A click into
an obstacle shows the daemon's reason and draws no path. Where the
goals are on the floor is computed here from the rig's calibration, not read from the page."""

from __future__ import annotations

import math

import numpy as np
import pytest
from selenium.webdriver.common.action_chains import ActionChains

from rigctl.apps.testing import wait_for
from rigctl.core.config import load_rig
from tests.browser.pages import bench_daemon, click, js, open_console, wait_page
from tests.e2e.test_click_goal import first_plan


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    yield from bench_daemon("six-coil", tmp_path_factory)


def run_first_plan(daemon) -> None:
    """The short run that tells the daemon where the magnets are (through its client)."""
    with daemon.client() as client:
        client.timeout_s = 30.0
        client.execute(client.load(first_plan()))
        client.wait_state("running", "idle", timeout_s=60.0)
        client.wait_state("idle", timeout_s=120.0)
        wait_for(lambda: client.status()["run"] is None and client.status()["tracked"], 30.0,
                 "the run ended and the daemon kept where it left the magnets")


def offset_of(driver, point_px) -> tuple[int, int]:
    """Where the camera's pixel `point_px` is drawn, from the overlay's centre in CSS px (the
    overlay fits the camera's picture into its box as the canvas does: contain, centred)."""
    box = js(driver, "(() => { const r = document.getElementById('goals-overlay')"
                     ".getBoundingClientRect(); return [r.width, r.height]; })()")
    width, height = js(driver, "rigctlConsole.hello.rig.camera.resolution")
    scale = min(box[0] / width, box[1] / height)
    return round((point_px[0] - width / 2) * scale), round((point_px[1] - height / 2) * scale)


def click_camera_px(driver, point_px) -> None:
    """A real pointer click where the camera's pixel `point_px` is drawn on the page."""
    svg = driver.find_element("id", "goals-overlay")
    ActionChains(driver).move_to_element_with_offset(svg, *offset_of(driver, point_px)).click() \
        .perform()


def drag_camera_px(driver, from_px, to_px) -> None:
    """Press at `from_px`, move to `to_px` in a few steps, release (camera pixels)."""
    svg = driver.find_element("id", "goals-overlay")
    start, end = offset_of(driver, from_px), offset_of(driver, to_px)
    chain = ActionChains(driver).move_to_element_with_offset(svg, *start).click_and_hold()
    for k in (1, 2, 3):
        chain.move_to_element_with_offset(svg, round(start[0] + k * (end[0] - start[0]) / 3),
                                          round(start[1] + k * (end[1] - start[1]) / 3))
    chain.release().perform()


def test_click_agents_and_goals_see_the_paths_execute_and_reach(rig, browser, screenshots):
    daemon, backdoor = rig
    run_first_plan(daemon)
    calibration = load_rig(daemon.rig_path).camera.calibration
    driver = open_console(browser, daemon)
    tracked = wait_page(driver, "rigctlConsole.status.tracked", 30.0, "the tracked magnets")
    # two turns up for both magnets, from where the first run's plan left them
    goals_mm = [[x, y + 20.0] for x, y in first_plan()["expected"][-1]]
    goals_px = calibration.to_px(np.array(goals_mm))
    # agent #1's goal first clicked 40 px off, then dragged to where it belongs
    off = [goals_px[0], goals_px[1] + np.array([-40.0, 0.0])]
    for agent, goal in enumerate(off):
        click_camera_px(driver, tracked["positions_px"][agent])
        wait_page(driver, f"rigctlGoals.selected === {agent}", 5.0, f"agent #{agent} picked")
        click_camera_px(driver, goal)
    wait_page(driver, "rigctlGoals.goals.size === 2", 5.0, "both goals clicked")
    drag_camera_px(driver, off[1], goals_px[1])
    u, v = goals_px[1]
    plan = wait_page(driver, "rigctlGoals.plan && rigctlGoals.goals.size === 2 && Math.hypot("
                     f"rigctlGoals.plan.goals_px[1][0] - {u}, rigctlGoals.plan.goals_px[1][1] - {v})"
                     " < 3 && rigctlGoals.plan", 60.0, "a plan to both goals, the dragged one's too")
    # the clicked goals, as the daemon read them: where they were clicked, to a pixel's worth
    mm_per_px = float(np.max(calibration.mm_per_px(goals_px)))
    for agent, goal in enumerate(goals_mm):
        assert math.dist(plan["goals_mm"][agent], goal) < 2 * mm_per_px, (plan["goals_mm"], goals_mm)
    # the planned paths drawn: one polyline per magnet, from the magnet to its goal
    drawn = js(driver, "[...document.querySelectorAll('#goals-overlay polyline.planned-path')]"
                       ".map(p => [...p.points].map(q => [q.x, q.y]))")
    assert len(drawn) == 2
    tolerance_px = plan["plan"]["tolerance_mm"] / mm_per_px
    for agent, path in enumerate(drawn):
        assert math.dist(path[0], tracked["positions_px"][agent]) < 0.5
        assert math.dist(path[-1], goals_px[agent]) < tolerance_px + 2.0, (path, goals_px)
    screenshots(driver, "six-coil-click-a-goal")
    wait_page(driver, "!document.getElementById('goals-execute').disabled", 10.0, "execute enabled")
    click(driver, "goals-execute")
    wait_page(driver, "rigctlConsole.state === 'running'", 30.0, "the run started")
    wait_page(driver, "rigctlConsole.status.state === 'idle' && !rigctlConsole.status.run && "
              f"(rigctlConsole.status.last_run || {{}}).plan_id === '{plan['plan_id']}'", 120.0,
              "the plan's run ended")
    last = js(driver, "rigctlConsole.status.last_run")
    assert last["plan_id"] == plan["plan_id"] and last["reached"], last
    truth = backdoor.request("truth")["agents"]
    for agent, real in enumerate(truth):
        # within the plan's tolerance of the goal the daemon read from the click
        assert math.dist(real, plan["goals_mm"][agent]) <= plan["plan"]["tolerance_mm"], truth


def test_a_goal_in_an_obstacle_says_why_and_draws_no_path(rig, browser):
    daemon, _ = rig
    with daemon.client() as client:
        if not client.status()["tracked"]:
            run_first_plan(daemon)
    calibration = load_rig(daemon.rig_path).camera.calibration
    driver = open_console(browser, daemon)
    tracked = wait_page(driver, "rigctlConsole.status.tracked", 30.0, "the tracked magnets")
    click_camera_px(driver, tracked["positions_px"][0])
    wait_page(driver, "rigctlGoals.selected === 0", 5.0, "agent #0 picked")
    click_camera_px(driver, calibration.to_px(np.array([[200.0, 160.0]]))[0])  # fig4's wall
    reason = wait_page(driver, "rigctlGoals.reason", 30.0, "the daemon's reason")
    assert "in an obstacle" in reason and "goal of agent #0" in reason
    assert "in an obstacle" in driver.find_element("id", "goals-reply").text
    assert js(driver, "document.querySelectorAll('#goals-overlay polyline.planned-path').length") == 0
    assert js(driver, "document.getElementById('goals-execute').disabled")
