"""`ccrp dashboard` as a user runs it, and Debian's chromium driving its page (headless, selenium
through Debian's chromedriver): shared by the browser tests of the ROS 1 and the ROS 2 fleet.

Selenium is imported only when a browser starts, so a module that uses these helpers imports
without it; MISSING says why a browser test cannot run here (None: it can)."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import pytest

from tests.conftest import ROOT

if not (shutil.which("chromium") and shutil.which("chromedriver")):
    MISSING: str | None = "needs Debian's chromium and chromium-driver (scripts/setup.sh installs them)"
elif importlib.util.find_spec("selenium") is None:
    MISSING = "needs selenium (`pip install -e .[dev]`)"
elif importlib.util.find_spec("fastapi") is None:
    MISSING = "needs the dashboard's web stack (`pip install -e .[dashboard]`)"
else:
    MISSING = None


@contextmanager
def running_dashboard(fleet) -> Iterator[dict]:
    """`ccrp dashboard` on the fleet's inventory, its URL (with the token) read from its stderr;
    stopped with Ctrl-C's signal at the end, killed if it does not stop."""
    log = fleet.tmp / "dashboard.log"
    with log.open("wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "ccrp_cli", "dashboard", "-i", str(fleet.inventory), "--bind", "127.0.0.1:0",
             "--interval", "2"],
            cwd=ROOT, env=fleet.env(), stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
    try:
        url = None
        deadline = time.monotonic() + 30
        while url is None:
            lines = [ln.strip() for ln in log.read_text().splitlines()]
            url = next((ln for ln in lines if ln.startswith("http://127.0.0.1:") and "?token=" in ln), None)
            if url is None:
                assert proc.poll() is None, f"ccrp dashboard exited {proc.returncode}:\n{log.read_text()}"
                assert time.monotonic() < deadline, f"no URL printed within 30 s:\n{log.read_text()}"
                time.sleep(0.2)
        yield {"url": url, "base": url.split("?")[0], "token": url.split("?token=")[1], "log": log, "proc": proc}
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)


@contextmanager
def chromium(scratch: Path):
    """A headless chromium; its profile and the scratch files it leaves go to `scratch`, not /tmp."""
    from selenium import webdriver

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                "--window-size=1400,820", "--no-first-run", "--disable-extensions",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-default-apps", "--metrics-recording-only", "--no-proxy-server"):
        options.add_argument(arg)
    options.add_argument(f"--user-data-dir={scratch / 'profile'}")
    service = webdriver.ChromeService(executable_path=shutil.which("chromedriver"), log_output=subprocess.DEVNULL,
                                      env={**os.environ, "TMPDIR": str(scratch)})
    driver = webdriver.Chrome(options=options, service=service)
    try:
        yield driver
    finally:
        driver.quit()


def cell(driver, robot: str, col: str) -> str:
    from selenium.common.exceptions import StaleElementReferenceException
    from selenium.webdriver.common.by import By

    for attempt in range(5):
        found = driver.find_elements(By.CSS_SELECTOR, f'tr[data-robot="{robot}"] td[data-col="{col}"]')
        try:
            return found[0].text if found else ""
        except StaleElementReferenceException:  # the page redrew the row between the find and the read
            if attempt == 4:                     # (it refreshes every second; run 42 met it once)
                raise
    return ""


def wait(driver, what: str, until, timeout: float):
    from selenium.common.exceptions import StaleElementReferenceException
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    try:
        # A row re-rendered between finding a cell and reading it: look again at the next poll.
        return WebDriverWait(driver, timeout, poll_frequency=0.25,
                             ignored_exceptions=[StaleElementReferenceException]).until(lambda d: until(d))
    except Exception:  # noqa: BLE001 - a clear message with what the page showed
        body = driver.find_element(By.TAG_NAME, "body").text
        pytest.fail(f"{what}: not within {timeout:.0f} s; the page showed:\n{body[:3000]}")


def press(driver, robot: str, button: str, label: str) -> None:
    """Click a button of a robot's row. The page renders its rows anew at every status event (every
    2 s here): a button found just before that is gone when clicked, so find it again."""
    from selenium.common.exceptions import StaleElementReferenceException
    from selenium.webdriver.common.by import By

    for _ in range(20):
        try:
            found = driver.find_element(By.CSS_SELECTOR, f'tr[data-robot="{robot}"] td.actions {button}')
            assert found.text == label, found.text
            found.click()
            return
        except StaleElementReferenceException:
            time.sleep(0.1)
    pytest.fail(f"{robot}'s {label} button: re-rendered at every try")


def motor_log(fleet, robot: str) -> list[dict]:
    """The simulated robot's demo node's motion log: the commands it received on /cmd_vel, and the
    stops its deadman made (`"deadman": true`) when no command came for 0.5 s while moving."""
    rc, out = fleet.container("robot-sim", robot).exec_run(["cat", "/var/log/ccrp-sim-cmd_vel.log"])
    return [json.loads(line) for line in out.decode().splitlines() if line.strip()] if rc == 0 else []


def received_commands(fleet, robot: str) -> list[dict]:
    """What the simulated robot's demo node logged receiving on /cmd_vel (its deadman's stops left out)."""
    return [c for c in motor_log(fleet, robot) if not c.get("deadman")]
