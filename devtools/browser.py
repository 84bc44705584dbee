"""Headless Chromium for the tests that look at a page: the live page
(tests/moonraker/test_page.py) and Mainsail and Fluidd (tests/ui), with
Debian's chromium and chromium-driver (.ci/run installs them)."""

from __future__ import annotations

import shutil
from typing import Optional

ARGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
        "--no-first-run", "--disable-background-networking",
        "--disable-component-update", "--disable-sync")


def missing_reason() -> Optional[str]:
    """Why no browser can be started here, in one line, or None."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install -e '.[dev]')"
    for name in ("chromium", "chromedriver"):
        if shutil.which(name) is None:
            return (f"{name} is not installed (Debian: apt-get install chromium "
                    f"chromium-driver; .ci/run does it)")
    return None


def chrome(width: int = 1400, height: int = 1100, performance_log: bool = False):
    """A headless Chromium driven through Debian's chromedriver (named
    explicitly: selenium's own manager would download one), its browser log
    kept for the JavaScript errors a page raised; the performance log too
    when asked (the network requests a page made). Call missing_reason()
    first."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for arg in (*ARGS, f"--window-size={width},{height}"):
        options.add_argument(arg)
    logs = {"browser": "ALL", **({"performance": "ALL"} if performance_log else {})}
    options.set_capability("goog:loggingPrefs", logs)
    return webdriver.Chrome(options=options,
                            service=Service(shutil.which("chromedriver")))
