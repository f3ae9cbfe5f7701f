"""A small headless-Chromium driver for the browser tests, over the Chrome DevTools Protocol (CDP).

Test helper, not a test file. The binary is Debian's ``chromium`` (``bash .ci/install-browser`` installs it
when it may); without one the ``browser`` fixture skips, naming the install command. The protocol goes over
one websocket (``websockets.sync.client``); no Selenium, no Playwright download.

Use from a test module::

    from browser import browser  # noqa: F401 - the fixture

    def test_page(browser):  # noqa: F811
        browser.goto(url)                                      # waits for the load event
        assert browser.evaluate("document.title") == "M3T"     # JSON-able results, promises awaited
        browser.wait_for("document.querySelector('video').readyState >= 1", timeout=10)
        browser.screenshot("dashboard.png", full_page=True)     # -> tests/artifacts/dashboard.png
        assert browser.console_errors == [] and browser.failed_requests == []

``browser`` is a :class:`Page` (1280x900 viewport) in a fresh browser context of its own (no cookies or
localStorage from another test); the Chromium process behind it is started once per test session.
:func:`launch` gives the same objects outside pytest (``with launch() as chromium: page = chromium.new_page()``).

What a page collects, from the moment it is opened (``clear()`` empties both lists):

- ``console_errors``: ``console.error`` / ``console.assert`` calls, uncaught exceptions and unhandled
  rejections, and the browser's own error log entries (CSP, blocked content ...), one string each, with the
  script location when the browser gives one;
- ``failed_requests``: requests that failed (``net::ERR_...``) and responses with an HTTP status >= 400, as
  ``"<url>: <reason>"``. Not failures: requests the page itself cancelled (a video's aborted range request)
  and the browser's own probe for ``/favicon.ico``. The browser also logs each failed load as a console
  error; those entries are left out of ``console_errors``, so that each failure is reported once, here.

Screenshots go to ``tests/artifacts/`` (``M3T_TEST_ARTIFACTS`` overrides; the folder is git-ignored).
``M3T_CHROMIUM`` names a binary to use instead of the first of ``chromium``, ``chromium-browser``,
``google-chrome`` on PATH.
"""
from __future__ import annotations

import base64
import inspect
import itertools
import json
import os
import shutil
import signal
import subprocess
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest

ROOT = Path(__file__).resolve().parents[1]
BINARIES = ("chromium", "chromium-browser", "google-chrome")
INSTALL_HINT = "run `sudo apt-get install chromium` (or bash .ci/install-browser)"
VIEWPORT = (1280, 900)
_LISTENING = "DevTools listening on "


class BrowserError(RuntimeError):
    """The browser could not be started, or a DevTools command failed."""


def find_chromium() -> str | None:
    """Path of the Chromium binary to drive (``M3T_CHROMIUM``, else the first of :data:`BINARIES` on PATH)."""
    named = os.environ.get("M3T_CHROMIUM")
    if named:
        return shutil.which(named)
    return next((path for path in map(shutil.which, BINARIES) if path), None)


def artifacts_dir() -> Path:
    """Where tests leave files for people to look at (``M3T_TEST_ARTIFACTS``, default ``tests/artifacts``)."""
    folder = Path(os.environ.get("M3T_TEST_ARTIFACTS") or ROOT / "tests" / "artifacts")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


class Chromium:
    """One headless Chromium process and its browser-level DevTools websocket; pages are multiplexed on it
    (flat sessions), so events of every page arrive here and are handed to the page they belong to."""

    def __init__(self, binary: str | None = None, *, timeout: float = 30.0):
        from websockets.sync.client import connect

        self.binary = binary or find_chromium()
        if not self.binary:
            raise BrowserError(f"headless Chromium not found: {INSTALL_HINT}")
        self.profile = Path(tempfile.mkdtemp(prefix="m3t-chromium-"))
        self._log_path = self.profile / "stderr.log"
        self._ids = itertools.count(1)
        self._pages: dict[str, Page] = {}
        self._ws = None
        try:
            with open(self._log_path, "wb") as log:
                # Own process group: close() ends the launcher script, the browser and its helpers at once.
                self._process = subprocess.Popen(
                    [self.binary, "--headless=new", "--no-sandbox", "--disable-gpu", "--remote-debugging-port=0",
                     f"--user-data-dir={self.profile}", "--no-first-run", "--no-default-browser-check",
                     "--mute-audio", f"--window-size={VIEWPORT[0]},{VIEWPORT[1]}", "about:blank"],
                    stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=log, start_new_session=True)
        except OSError:
            shutil.rmtree(self.profile, ignore_errors=True)
            raise
        try:
            url = self._wait_for_endpoint(timeout)
            # websockets >= 15 would route 127.0.0.1 through an HTTP(S)_PROXY of the environment
            options = {"proxy": None} if "proxy" in inspect.signature(connect).parameters else {}
            self._ws = connect(url, max_size=None, open_timeout=timeout, ping_interval=None, **options)
        except BaseException:
            self.close()
            raise

    def _wait_for_endpoint(self, timeout: float) -> str:
        """The ``ws://127.0.0.1:<port>/devtools/browser/<id>`` URL Chromium prints on stderr once it listens."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            text = self._log_path.read_text(errors="replace")
            for line in text.splitlines():
                if line.startswith(_LISTENING):
                    return line[len(_LISTENING):].strip()
            if self._process.poll() is not None:
                raise BrowserError(f"{self.binary} exited with code {self._process.returncode} before listening:\n"
                                   + "\n".join(text.splitlines()[-15:]))
            time.sleep(0.05)
        raise BrowserError(f"{self.binary} printed no '{_LISTENING}ws://...' line within {timeout:.0f} s; "
                           f"its stderr:\n" + "\n".join(self._log_path.read_text(errors="replace").splitlines()[-15:]))

    @property
    def alive(self) -> bool:
        return self._ws is not None and self._process.poll() is None

    # -- protocol -------------------------------------------------------------------------------------------
    def send(self, method: str, params: dict | None = None, session: str | None = None,
             timeout: float = 30.0) -> dict:
        """Send one command and return its result; events that arrive meanwhile go to their pages."""
        if self._ws is None:
            raise BrowserError(f"{method}: the browser is closed")
        message_id = next(self._ids)
        message: dict[str, Any] = {"id": message_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        from websockets.exceptions import ConnectionClosed

        try:
            self._ws.send(json.dumps(message))
        except ConnectionClosed as error:
            raise self._gone(error) from error
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            reply = self._receive(left) if left > 0 else None
            if reply is None:
                raise TimeoutError(f"{method}: no answer from the browser within {timeout:.0f} s")
            if reply.get("id") == message_id:
                if "error" in reply:
                    raise BrowserError(f"{method}: {reply['error'].get('message')} {reply['error'].get('data', '')}")
                return reply.get("result", {})

    def pump(self, seconds: float = 0.0) -> None:
        """Hand the events that arrive within ``seconds`` (those already here when 0) to their pages."""
        deadline = time.monotonic() + seconds
        while self._ws is not None and self._receive(max(0.0, deadline - time.monotonic())) is not None:
            pass

    def _receive(self, timeout: float) -> dict | None:
        """The next message (``None`` when none came within ``timeout``); events are dispatched on the way."""
        from websockets.exceptions import ConnectionClosed

        try:
            message = json.loads(self._ws.recv(timeout=timeout))
        except TimeoutError:
            return None
        except ConnectionClosed as error:
            raise self._gone(error) from error
        if "method" in message:
            page = self._pages.get(message.get("sessionId", ""))
            if page is not None:
                page._on_event(message["method"], message.get("params", {}))
        return message

    def _gone(self, error: Exception) -> BrowserError:
        self._ws = None
        return BrowserError(f"{self.binary} closed the DevTools connection ({error}); the end of its stderr:\n"
                            + "\n".join(self._log_path.read_text(errors="replace").splitlines()[-15:]))

    # -- pages ----------------------------------------------------------------------------------------------
    def new_page(self) -> Page:
        """A tab in a fresh browser context (own cookies and storage), with Page/Runtime/Log/Network enabled."""
        context = self.send("Target.createBrowserContext", {"disposeOnDetach": True})["browserContextId"]
        target = self.send("Target.createTarget", {"url": "about:blank", "browserContextId": context})["targetId"]
        session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        page = Page(self, session, target, context)
        self._pages[session] = page
        for domain in ("Page", "Runtime", "Log", "Network"):
            page.send(f"{domain}.enable")
        page.send("Emulation.setDeviceMetricsOverride",
                  {"width": VIEWPORT[0], "height": VIEWPORT[1], "deviceScaleFactor": 1, "mobile": False})
        return page

    def close(self) -> None:
        """End the browser's process group and remove its profile folder (safe to call twice)."""
        if self._ws is not None:
            try:
                self._ws.close()
            except Exception:  # noqa: BLE001 - the browser may be gone already; it is killed below either way
                pass
            self._ws = None
        if self._process.poll() is None:
            for sig, wait in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
                try:
                    os.killpg(self._process.pid, sig)
                except ProcessLookupError:
                    break
                try:
                    self._process.wait(wait)
                    break
                except subprocess.TimeoutExpired:
                    continue
        # helpers (zygote, renderers) of the group may outlive the launcher by a moment
        try:
            os.killpg(self._process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        shutil.rmtree(self.profile, ignore_errors=True)

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Page:
    """One tab: navigate, evaluate JavaScript, wait, take screenshots; collects console errors and failed
    requests (see the module docstring)."""

    def __init__(self, chromium: Chromium, session: str, target: str, context: str):
        self.chromium = chromium
        self.session = session
        self.target = target
        self.context = context
        self._console_errors: list[str] = []
        self._failed_requests: list[str] = []
        self._urls: dict[str, str] = {}  # requestId -> URL (loadingFailed names only the id)
        self._loads = 0

    def send(self, method: str, params: dict | None = None, timeout: float = 30.0) -> dict:
        """A raw DevTools command to this tab (``page.send("Page.reload")``)."""
        return self.chromium.send(method, params, self.session, timeout)

    # -- what the page reports ------------------------------------------------------------------------------
    @property
    def console_errors(self) -> list[str]:
        self.chromium.pump()
        return list(self._console_errors)

    @property
    def failed_requests(self) -> list[str]:
        self.chromium.pump()
        return list(self._failed_requests)

    def clear(self) -> None:
        """Forget the console errors and failed requests collected so far."""
        self.chromium.pump()
        self._console_errors.clear()
        self._failed_requests.clear()

    def _on_event(self, method: str, params: dict) -> None:
        if method == "Page.loadEventFired":
            self._loads += 1
        elif method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            text = " ".join(_remote_text(arg) for arg in params.get("args", []))
            self._console_errors.append(f"console.{params['type']}: {text}{_where(params.get('stackTrace'))}")
        elif method == "Runtime.exceptionThrown":
            details = params.get("exceptionDetails", {})
            text = details.get("exception", {}).get("description") or details.get("text", "exception")
            self._console_errors.append(f"uncaught {text.splitlines()[0]}{_where(details.get('stackTrace'), details)}")
        elif method == "Log.entryAdded":
            entry = params.get("entry", {})
            if entry.get("level") == "error" and entry.get("source") != "network":  # network: failed_requests
                self._console_errors.append(f"{entry.get('source')}: {entry.get('text')}"
                                            + (f" ({entry['url']})" if entry.get("url") else ""))
        elif method == "Network.requestWillBeSent":
            self._urls[params["requestId"]] = params.get("request", {}).get("url", "?")
        elif method == "Network.responseReceived":
            response = params.get("response", {})
            if response.get("status", 0) >= 400 and not _favicon_probe(response.get("url", ""), params.get("type")):
                self._failed_requests.append(f"{response.get('url')}: HTTP {response['status']} "
                                             f"{response.get('statusText', '')}".rstrip())
        elif method == "Network.loadingFailed" and not params.get("canceled"):
            url = self._urls.get(params["requestId"], "?")
            if not _favicon_probe(url, params.get("type")):
                reason = params.get("blockedReason") or params.get("errorText", "failed")
                self._failed_requests.append(f"{url}: {reason}")

    # -- actions --------------------------------------------------------------------------------------------
    def goto(self, url: str, wait_until_load: bool = True, timeout: float = 30.0) -> None:
        """Navigate to ``url`` (``http://``, ``file://`` ...); by default wait for its ``load`` event."""
        self.chromium.pump()
        loads = self._loads
        result = self.send("Page.navigate", {"url": url}, timeout)
        if result.get("errorText"):
            raise BrowserError(f"cannot open {url}: {result['errorText']}")
        if not wait_until_load or not result.get("loaderId"):  # a same-document navigation has no load event
            return
        deadline = time.monotonic() + timeout
        while self._loads == loads:
            if time.monotonic() > deadline:
                raise TimeoutError(f"{url}: no load event within {timeout:.0f} s")
            self.chromium.pump(0.05)

    def evaluate(self, expression: str, timeout: float = 30.0) -> Any:
        """Value of a JavaScript expression (promises awaited, results returned as JSON values)."""
        result = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                "awaitPromise": True, "userGesture": True}, timeout)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            text = details.get("exception", {}).get("description") or details.get("text")
            raise BrowserError(f"evaluating {expression!r} threw: {text}")
        return result.get("result", {}).get("value")

    def wait_for(self, predicate: str, timeout: float = 10.0, interval: float = 0.1) -> Any:
        """Poll the JavaScript expression ``predicate`` until it is truthy; returns its value."""
        deadline = time.monotonic() + timeout
        while True:
            value = self.evaluate(predicate)
            if value:
                return value
            if time.monotonic() > deadline:
                raise TimeoutError(f"still falsy after {timeout:.0f} s ({value!r}): {predicate}")
            self.chromium.pump(interval)

    def screenshot(self, path: str | Path, full_page: bool = False) -> Path:
        """Save a PNG of the viewport (or the whole page); a relative path lands in :func:`artifacts_dir`."""
        path = Path(path)
        if not path.is_absolute():
            path = artifacts_dir() / path
        path.parent.mkdir(parents=True, exist_ok=True)
        params: dict[str, Any] = {"format": "png"}
        if full_page:
            size = self.send("Page.getLayoutMetrics")["cssContentSize"]
            params.update(captureBeyondViewport=True,
                          clip={"x": 0, "y": 0, "width": size["width"], "height": size["height"], "scale": 1})
        path.write_bytes(base64.b64decode(self.send("Page.captureScreenshot", params)["data"]))
        return path

    def close(self) -> None:
        """Close the tab and drop its browser context."""
        if self.chromium._pages.pop(self.session, None) is None:
            return
        try:
            self.chromium.send("Target.closeTarget", {"targetId": self.target})
            self.chromium.send("Target.disposeBrowserContext", {"browserContextId": self.context})
        except (BrowserError, TimeoutError):
            pass  # the context went with the tab (disposeOnDetach), or the browser is gone


def _favicon_probe(url: str, resource_type: str | None) -> bool:
    """The browser's own request for ``/favicon.ico`` (type ``Other``), which no page asked for."""
    return resource_type == "Other" and urlsplit(url).path == "/favicon.ico"


def _remote_text(obj: dict) -> str:
    """Readable text of a Runtime.RemoteObject (a console.error argument)."""
    if "value" in obj:
        return obj["value"] if isinstance(obj["value"], str) else json.dumps(obj["value"])
    return obj.get("description") or obj.get("unserializableValue") or obj.get("type", "?")


def _where(stack: dict | None, details: dict | None = None) -> str:
    frames = (stack or {}).get("callFrames") or []
    if frames:
        return f" ({frames[0].get('url') or '<inline>'}:{frames[0].get('lineNumber', 0) + 1})"
    if details and details.get("url"):
        return f" ({details['url']}:{details.get('lineNumber', 0) + 1})"
    return ""


@contextmanager
def launch(binary: str | None = None) -> Iterator[Chromium]:
    """A headless Chromium for the block; ends its processes and removes its profile afterwards."""
    chromium = Chromium(binary)
    try:
        yield chromium
    finally:
        chromium.close()


def require_chromium() -> str:
    """The Chromium binary, or skip the calling test with the command that installs one."""
    binary = find_chromium()
    if binary is None:
        pytest.skip(f"headless Chromium not found: {INSTALL_HINT}")
    return binary


_SESSION_BROWSER = pytest.StashKey[Chromium]()


@pytest.fixture
def browser(request: pytest.FixtureRequest) -> Iterator[Page]:
    """A fresh :class:`Page` of the session's headless Chromium; skips when there is no Chromium binary."""
    binary = require_chromium()
    stash = request.config.stash
    chromium = stash.get(_SESSION_BROWSER, None)
    if chromium is None or not chromium.alive:  # first use, or a crash in an earlier test
        chromium = stash[_SESSION_BROWSER] = Chromium(binary)
        request.config.add_cleanup(chromium.close)
    page = chromium.new_page()
    try:
        yield page
    finally:
        page.close()
