"""The run's page in a real browser (Debian's headless Chromium through chromedriver, with selenium): a tiny day on a
feeder run with ``--view``, watched until it has settled, and what the page's DOM shows compared with the recording;
and a recording played into the same page, paused and moved back. Each leaves a screenshot in its tmp_path.
The page is waited for on its DOM (``data-*`` of its body and cells), never for a time."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from dmosim.results.tables import tables
from messages.recording import read_recording
from tests.conftest import Fifo

pytestmark = pytest.mark.slow
TWO_DAYS = Path(__file__).resolve().parents[1] / "data" / "schema-v2-two-days.mcap"
CHROMIUM, DRIVER = shutil.which("chromium") or "/usr/bin/chromium", shutil.which("chromedriver") or "/usr/bin/chromedriver"
PAGE_S = 180.0  # a tiny day of processes on a loaded machine: the wait ends as soon as the DOM says so


@pytest.fixture
def browser():
    if not (os.path.exists(CHROMIUM) and os.path.exists(DRIVER)) and not os.environ.get("CI"):
        pytest.skip("Debian's chromium and chromium-driver are not installed (.ci/run installs them)")
    from selenium import webdriver  # noqa: PLC0415
    from selenium.webdriver.chrome.service import Service  # noqa: PLC0415

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for flag in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1400,1500"):
        options.add_argument(flag)
    driver = webdriver.Chrome(options=options, service=Service(DRIVER))
    try:
        yield driver
    finally:
        driver.quit()


def until(driver, script: str, timeout_s: float = PAGE_S):
    """Wait until the JavaScript expression ``script`` is truthy in the page; its value."""
    from selenium.webdriver.support.ui import WebDriverWait  # noqa: PLC0415

    return WebDriverWait(driver, timeout_s, poll_frequency=0.1).until(lambda d: d.execute_script(f"return {script}"))


# What the page shows, read in one go (the page redraws whole panels as pages come): the phase and market day, each
# award cell (agent, hour, MW), each bus price cell (bus, hour, $/MWh) and each bill (agent, $)
SHOWN = """
const all = (q, f) => [...document.querySelectorAll(q)].map(f);
return {phase: document.getElementById('phase').textContent,
        market_day: document.getElementById('market-day').textContent,
        awards: all('#awards td[data-award]', (c) => [c.dataset.agent, c.dataset.hour, c.dataset.award]),
        prices: all('#bus-prices td[data-price]', (c) => [c.dataset.bus, c.dataset.hour, c.dataset.price]),
        bills: all('#bills tr[data-bill]', (r) => [r.dataset.agent, r.dataset.bill])};
"""


def stopped(process: subprocess.Popen) -> int:
    """SIGTERM (as Ctrl-C) and its exit code; killed with all it started if it does not leave."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(60)
    except subprocess.TimeoutExpired:
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        raise


def test_a_run_with_view_shows_its_phase_awards_bus_prices_and_bills_as_the_recording_has_them(tmp_path, fifo,
                                                                                               browser):
    out = tmp_path / "run"
    printed = Fifo(tmp_path / "stdout.fifo")  # the result, read as it is printed: then the run lingers on its page
    with open(printed.path, "w") as stdout, open(tmp_path / "stderr", "w") as stderr:
        run = subprocess.Popen(
            [sys.executable, "-m", "dmosim", "run", "--agents", "2", "--scenarios", "1", "--subperiods", "1",
             "--feeder", "feeder5", "--view", "--view-url-file", str(fifo.path), "--out", str(out), "--json",
             "--quiet"], stdout=stdout, stderr=stderr, stdin=subprocess.DEVNULL, process_group=0)
    try:
        url = fifo.line(run.pid, PAGE_S)
        assert url.startswith("http://127.0.0.1:")
        browser.get(url)
        until(browser, "document.body.dataset.settled === 'yes' && "
                       "document.querySelectorAll('#bills tr[data-settled=yes]').length === 2")
        browser.save_screenshot(str(tmp_path / "live.png"))
        shown = browser.execute_script(SHOWN)
        lines = [printed.line(run.pid, PAGE_S)]
        while lines[-1] != "}":  # --json: one object, its closing brace alone on the last line
            lines.append(printed.line(run.pid, PAGE_S))
        assert run.poll() is None  # the run is over and its page still up, until Ctrl-C or SIGTERM
    finally:
        code = stopped(run)
        printed.close()
    assert code == 0, (tmp_path / "stderr").read_text()[-3000:]
    result = json.loads("\n".join(lines))
    t = tables(read_recording(result["recording"]))
    assert shown["phase"] == "settlement" and shown["market_day"] == t["days"]["market_day"][0]
    awards = {(a, int(h)): float(v) for a, h, v in shown["awards"]}
    prices = {(b, int(h)): float(v) for b, h, v in shown["prices"]}
    assert len(awards) == 48 and len(prices) == 5 * 24
    for row in t["hours"].itertuples():
        assert awards[row.agent, row.hour] == pytest.approx(row.p_sch_mw, abs=1e-3)
        assert prices[row.bus, row.hour] == pytest.approx(row.clearing_price_per_mwh, abs=0.01)  # its bus's price
    bills = {a: float(v) for a, v in shown["bills"]}
    assert bills == pytest.approx(t["days"].set_index("agent")["total"].to_dict(), abs=0.01)


def test_a_recording_plays_into_the_same_page_and_moves_back_to_its_start(tmp_path, fifo, browser):
    with open(tmp_path / "stderr", "w") as stderr:
        view = subprocess.Popen([sys.executable, "-m", "dmosim", "view", str(TWO_DAYS), "--rate", "1000",
                                 "--url-file", str(fifo.path)], stdout=subprocess.DEVNULL, stderr=stderr,
                                stdin=subprocess.DEVNULL, process_group=0)
    try:
        browser.get(fifo.line(view.pid, PAGE_S))
        until(browser, "document.body.dataset.ended === 'yes' && document.body.dataset.settled === 'yes'")
        browser.save_screenshot(str(tmp_path / "replay.png"))
        shown = browser.execute_script(SHOWN)
        assert browser.execute_script("return !document.getElementById('controls').hidden")
        browser.execute_script("control({pause: true, seek: 0})")  # what the play button and the slider send
        until(browser, "document.body.dataset.phase === 'registration' && "
                       "document.getElementById('play').dataset.paused === 'yes'")
        left = browser.execute_script(SHOWN)["bills"]
    finally:
        code = stopped(view)
    assert code == 0, (tmp_path / "stderr").read_text()[-3000:]
    t = tables(read_recording(TWO_DAYS))
    assert shown["market_day"] == "2026-07-07"
    bills = {a: float(v) for a, v in shown["bills"]}
    assert bills == pytest.approx(t["days"].groupby("agent")["total"].sum().to_dict(), abs=0.01)
    assert left == []  # at the start of the recording nobody has registered yet
