"""report.html in headless Chromium: every image loads and no request leaves the machine.

Chromium is driven over the DevTools protocol on a pipe (--remote-debugging-pipe: fd 3 in, fd 4 out), so the test
needs no driver package: it logs every request the page makes (Network.requestWillBeSent) and asks the page for
each image's load state. Host names resolve nowhere (--host-resolver-rules), so a page that needed the network
would also visibly fail. CI installs Debian's `chromium-headless-shell`; without any Chromium the test is skipped.
"""

from __future__ import annotations

import fcntl
import json
import os
import select
import shutil
import subprocess
import tempfile
import time

import pytest
from support import FAST

import riskplan
from riskplan.experiments.reporting import build_report

CANDIDATES = (
    "chromium-headless-shell",
    "chromium",
    "chromium-browser",
    "chrome-headless-shell",
    "google-chrome",
    "headless_shell",
)
IMAGES = (
    "JSON.stringify(Array.from(document.images).map(i => "
    "({src: i.currentSrc.slice(0, 40), complete: i.complete, width: i.naturalWidth, height: i.naturalHeight})))"
)


def find_chromium() -> str | None:
    """$RISKPLAN_CHROMIUM, else the first Chromium-family binary on PATH."""
    explicit = os.environ.get("RISKPLAN_CHROMIUM")
    if explicit:
        return explicit
    return next((path for path in map(shutil.which, CANDIDATES) if path), None)


CHROMIUM = find_chromium()
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        CHROMIUM is None,
        reason="no Chromium binary found (looked for $RISKPLAN_CHROMIUM and "
        f"{', '.join(CANDIDATES)}); CI installs chromium-headless-shell",
    ),
]


class DevTools:
    """A headless Chromium and a flat DevTools session over --remote-debugging-pipe."""

    def __init__(self, binary: str, timeout: float = 60.0):
        self.deadline = time.monotonic() + timeout
        to_chrome_r, self._to_chrome = os.pipe()
        self._from_chrome, from_chrome_w = os.pipe()

        def wire_fds() -> None:  # in the child: our pipe ends become its fds 3 (commands) and 4 (replies)
            inbound = fcntl.fcntl(to_chrome_r, fcntl.F_DUPFD, 10)
            outbound = fcntl.fcntl(from_chrome_w, fcntl.F_DUPFD, 10)
            os.dup2(inbound, 3)
            os.dup2(outbound, 4)

        self.profile = tempfile.mkdtemp(prefix="riskplan-chromium-")
        self.proc = subprocess.Popen(
            [
                binary,
                "--headless",
                "--remote-debugging-pipe",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-dev-shm-usage",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-default-apps",
                "--disable-extensions",
                "--host-resolver-rules=MAP * ~NOTFOUND",
                f"--user-data-dir={self.profile}",
                "about:blank",
            ],
            pass_fds=(3, 4),
            preexec_fn=wire_fds,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        os.close(to_chrome_r)
        os.close(from_chrome_w)
        self._buffer = b""
        self._next_id = 0
        self.events: list[dict] = []

    def _receive(self, wanted) -> dict:
        while True:
            while b"\0" in self._buffer:
                raw, self._buffer = self._buffer.split(b"\0", 1)
                message = json.loads(raw)
                self.events.append(message)
                if wanted(message):
                    return message
            left = self.deadline - time.monotonic()
            if left <= 0:
                raise TimeoutError("Chromium did not answer in time")
            ready, _, _ = select.select([self._from_chrome], [], [], left)
            if ready:
                chunk = os.read(self._from_chrome, 1 << 20)
                if not chunk:
                    raise RuntimeError(f"Chromium exited: {self.proc.stderr.read().decode(errors='replace')[-2000:]}")
                self._buffer += chunk

    def call(self, method: str, params: dict | None = None, session: str | None = None) -> dict:
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._to_chrome, json.dumps(message).encode() + b"\0")
        reply = self._receive(lambda m, i=self._next_id: m.get("id") == i)
        if "error" in reply:
            raise RuntimeError(f"{method}: {reply['error']}")
        return reply["result"]

    def open(self, url: str) -> tuple[list[dict], list[str]]:
        """Load url; return the page's images (load state) and the URL of every request it made."""
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        self.call("Network.enable", {}, session)
        self.call("Page.enable", {}, session)
        self.call("Page.navigate", {"url": url}, session)
        self._receive(lambda m: m.get("method") == "Page.loadEventFired" and m.get("sessionId") == session)
        result = self.call("Runtime.evaluate", {"expression": IMAGES, "returnByValue": True}, session)
        requests = [
            e["params"]["request"]["url"]
            for e in self.events
            if e.get("method") == "Network.requestWillBeSent" and e.get("sessionId") == session
        ]
        return json.loads(result["result"]["value"]), requests

    def close(self) -> None:
        try:
            self.call("Browser.close")
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        self.proc.stderr.close()
        os.close(self._to_chrome)
        os.close(self._from_chrome)
        shutil.rmtree(self.profile, ignore_errors=True)


@pytest.fixture
def browser():
    tools = DevTools(CHROMIUM)
    yield tools
    tools.close()


def leaving(requests: list[str]) -> list[str]:
    """Requests for anything but the local file and embedded data."""
    return [url for url in requests if not url.startswith(("file://", "data:"))]


def test_report_opens_offline_with_every_image_loaded(tmp_path, browser):
    for name, extra in (("cvar", []), ("neutral", ["risk=neutral"]), ("team", ["experiment=paper_team"])):
        riskplan.train(riskplan.compose(FAST + extra), tmp_path / "runs" / name)
    page = build_report([tmp_path / "runs"], tmp_path / "report", ["png"])
    images, requests = browser.open(page.resolve().as_uri())
    # Figs. 1-4, reward distribution, risk frontier, team thetas, and each world (the team's starts are its own)
    assert len(images) == 9
    assert all(i["src"].startswith("data:image/png;base64,") for i in images)
    broken = [i for i in images if not (i["complete"] and i["width"] > 0 and i["height"] > 0)]
    assert not broken, broken
    assert requests and requests[0] == page.resolve().as_uri()
    assert not leaving(requests), leaving(requests)


def test_the_check_catches_a_page_that_needs_the_network(tmp_path, browser):
    """Control: the same check fails a page with a remote image (so a pass above means something)."""
    page = tmp_path / "remote.html"
    page.write_text('<!DOCTYPE html><html><body><img src="http://riskplan-test.invalid/figure.png"></body></html>')
    images, requests = browser.open(page.as_uri())
    assert leaving(requests) == ["http://riskplan-test.invalid/figure.png"]
    assert images[0]["width"] == 0
