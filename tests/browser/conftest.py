"""The operator console in a real browser: headless Chromium (Debian's `chromium` and
`chromium-driver`, which `.ci/run` installs; the driver is the one built for that browser)
driven by selenium, against `rigctl daemon --console` on each rig's emulated bench.

One bench and one daemon per test module (module-scoped); each test opens the pages it needs, in
browser windows of its own that are closed after it. Screenshots go to the test's tmp output (`screenshots` below); with
RIGCTL_CONSOLE_SCREENSHOTS=FOLDER they are copied there too (how docs/console/ is made).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

CHROMIUM = Path(os.environ.get("RIGCTL_CHROMIUM", "/usr/bin/chromium"))
CHROMEDRIVER = Path(os.environ.get("RIGCTL_CHROMEDRIVER", "/usr/bin/chromedriver"))


@pytest.fixture
def browser():
    """A factory of headless Chromium windows: `browser(width, height)`; all closed at the end of
    the test. (Module-wide, every page a test left open went on drawing the live camera: by the
    module's fifth test five Chromiums took a core between them and a page's socket timed out.)"""
    if not (CHROMIUM.exists() and CHROMEDRIVER.exists()):
        pytest.fail(f"the browser tests need {CHROMIUM} and {CHROMEDRIVER} (Debian's chromium "
                    "and chromium-driver: apt-get install -y chromium chromium-driver)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    drivers = []

    def open_window(width: int = 1280, height: int = 800):
        options = webdriver.ChromeOptions()
        options.binary_location = str(CHROMIUM)
        for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                    "--disable-gpu", f"--window-size={width},{height}", "--hide-scrollbars"):
            options.add_argument(arg)
        driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
        # the page's viewport is what it must fit: new headless Chromium keeps room for a browser
        # frame it does not draw (a 1280 x 720 window showed a 1280 x 577 page), so the window
        # is grown by what the viewport lacks
        driver.set_window_size(width, height)
        inner = driver.execute_script("return [window.innerWidth, window.innerHeight];")
        if inner != [width, height]:
            driver.set_window_size(2 * width - inner[0], 2 * height - inner[1])
        drivers.append(driver)
        return driver

    yield open_window
    for driver in drivers:
        driver.quit()


@pytest.fixture(scope="module")
def screenshots(tmp_path_factory) -> Callable[[object, str], Path]:
    folder = tmp_path_factory.mktemp("screenshots")
    copy_to = os.environ.get("RIGCTL_CONSOLE_SCREENSHOTS")

    def save(driver, name: str, full_page: bool = False) -> Path:
        """The window as the operator sees it; `full_page`: the whole page, plots included (the
        window grown to the page's height for the shot, then back)."""
        path = folder / f"{name}.png"
        size = driver.get_window_size()
        if full_page:
            height, inner = driver.execute_script(
                "return [document.documentElement.scrollHeight, window.innerHeight];")
            driver.set_window_size(size["width"], height + 20 + size["height"] - inner)
            driver.execute_script("return new Promise(r => requestAnimationFrame(() => r()));")
        driver.save_screenshot(str(path))
        if full_page:
            driver.set_window_size(size["width"], size["height"])
        if copy_to:
            Path(copy_to).mkdir(parents=True, exist_ok=True)
            shutil.copy(path, Path(copy_to) / path.name)
        return path

    save.folder = folder
    return save


