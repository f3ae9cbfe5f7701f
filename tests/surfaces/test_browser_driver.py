"""The headless-Chromium driver (tests/browser.py) sees what the browser tests rely on: console errors,
uncaught exceptions and failed requests (exactly those, nothing on a clean page), DOM values, an H.264 MP4
that the browser decodes, screenshots; and .ci/install-browser takes the right path on each kind of machine."""
from __future__ import annotations

import functools
import os
import struct
import subprocess
import threading
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np
import pytest

from browser import BrowserError, browser, find_chromium, require_chromium  # noqa: F401 - browser: the fixture

ROOT = Path(__file__).resolve().parents[2]
TABLE = "<table id='runs'><tr><th>stage</th><th>jpe</th></tr><tr><td>fit</td><td>9.3</td></tr></table>"
CLEAN = f"<!doctype html><html><head><title>clean</title></head><body>{TABLE}</body></html>"
BROKEN = f"""<!doctype html><html><head><title>broken</title></head><body>{TABLE}
<img src="missing.png">
<script>console.log("fine"); console.warn("only a warning"); console.error("deliberate", 42);</script>
<script>throw new Error("boom");</script>
<script>Promise.reject(new Error("not awaited"));</script>
</body></html>"""
COLOUR = (200, 40, 40)  # RGB of every frame of the test clip


@pytest.fixture
def served(tmp_path):
    """``tmp_path`` over HTTP on 127.0.0.1 (a same-origin page can read video pixels back from a canvas)."""
    handler = functools.partial(type("Quiet", (SimpleHTTPRequestHandler,), {"log_message": lambda *a: None}),
                                directory=str(tmp_path))
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def test_errors_and_failed_requests_are_collected(browser, tmp_path):  # noqa: F811
    (tmp_path / "broken.html").write_text(BROKEN)
    browser.goto((tmp_path / "broken.html").as_uri())
    browser.chromium.pump(0.3)  # late events
    errors = browser.console_errors
    assert len(errors) == 3, errors  # console.log / console.warn are not errors
    assert errors[0].startswith("console.error: deliberate 42") and "broken.html:3" in errors[0]
    assert errors[1].startswith("uncaught Error: boom") and "broken.html:4" in errors[1]
    assert errors[2].startswith("uncaught Error: not awaited") and "broken.html:5" in errors[2]
    assert browser.failed_requests == [f"{(tmp_path / 'missing.png').as_uri()}: net::ERR_FILE_NOT_FOUND"]
    browser.clear()
    assert browser.console_errors == [] and browser.failed_requests == []


def test_clean_page_and_dom_values(browser, tmp_path):  # noqa: F811
    (tmp_path / "clean.html").write_text(CLEAN)
    browser.goto((tmp_path / "clean.html").as_uri())
    assert browser.evaluate("document.title") == "clean"
    assert browser.evaluate("[...document.querySelectorAll('#runs td')].map(td => td.textContent)") == ["fit", "9.3"]
    assert browser.evaluate("new Promise(done => setTimeout(() => done({rows: 2}), 50))") == {"rows": 2}
    assert browser.evaluate("undefined") is None
    with pytest.raises(BrowserError, match="ReferenceError"):
        browser.evaluate("notDefined.x")
    with pytest.raises(TimeoutError, match="still falsy"):
        browser.wait_for("document.querySelectorAll('td').length > 2", timeout=0.3)
    browser.chromium.pump(0.2)
    assert browser.console_errors == [] and browser.failed_requests == []  # evaluate's own throw is not the page's


def test_http_error_status_is_a_failed_request(browser, tmp_path, served):  # noqa: F811
    (tmp_path / "clean.html").write_text(CLEAN)
    browser.goto(f"{served}/clean.html")
    assert browser.evaluate("fetch('nope.json').then(r => r.status)") == 404
    assert browser.failed_requests == [f"{served}/nope.json: HTTP 404 File not found"]
    assert browser.console_errors == []  # the browser's own "Failed to load resource" line is reported once, above


def test_pages_do_not_share_storage(browser, tmp_path, served):  # noqa: F811
    (tmp_path / "clean.html").write_text(CLEAN)
    browser.goto(f"{served}/clean.html")
    browser.evaluate("localStorage.setItem('mlflow.workflowType_v1', '\"machine_learning\"')")
    other = browser.chromium.new_page()
    try:
        other.goto(f"{served}/clean.html")
        assert other.evaluate("localStorage.getItem('mlflow.workflowType_v1')") is None
    finally:
        other.close()


def write_clip(path: Path, frames: int = 8, size: tuple[int, int] = (64, 48)) -> Path:
    """An H.264 (yuv420p) MP4 of ``frames`` solid :data:`COLOUR` frames, written like the project's videos."""
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(str(path), size, fps=10, codec="libx264", pix_fmt_out="yuv420p",
                                         macro_block_size=16, output_params=["-movflags", "+faststart"])
    writer.send(None)
    frame = np.empty((size[1], size[0], 3), np.uint8)
    frame[:] = COLOUR
    for _ in range(frames):
        writer.send(frame)
    writer.close()
    return path


def test_h264_mp4_is_decoded(browser, tmp_path, served):  # noqa: F811
    write_clip(tmp_path / "clip.mp4")
    (tmp_path / "video.html").write_text('<!doctype html><video src="clip.mp4" muted preload="auto"></video>')
    browser.goto(f"{served}/video.html")
    assert browser.evaluate("document.querySelector('video').canPlayType('video/mp4; codecs=\"avc1.42E01E\"')") \
        == "probably"
    browser.wait_for("document.querySelector('video').readyState >= 2", timeout=10)  # a frame is decoded
    video = browser.evaluate("(v => ({w: v.videoWidth, h: v.videoHeight, s: v.duration}))"
                             "(document.querySelector('video'))")
    assert video == {"w": 64, "h": 48, "s": pytest.approx(0.8, abs=0.05)}
    pixel = browser.evaluate("""(() => {
        const v = document.querySelector('video'), c = document.createElement('canvas');
        c.width = v.videoWidth; c.height = v.videoHeight;
        const g = c.getContext('2d'); g.drawImage(v, 0, 0);
        return Array.from(g.getImageData(32, 24, 1, 1).data.slice(0, 3));
    })()""")
    assert np.abs(np.array(pixel) - COLOUR).max() <= 12, pixel  # decoded, not only demuxed
    assert browser.console_errors == [] and browser.failed_requests == []


def png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    return struct.unpack(">II", data[16:24])


def test_screenshots(browser, tmp_path, monkeypatch):  # noqa: F811
    monkeypatch.setenv("M3T_TEST_ARTIFACTS", str(tmp_path / "artifacts"))
    (tmp_path / "tall.html").write_text(f"<!doctype html><body style='margin:0'><div style='height:2000px'>"
                                        f"{TABLE}</div></body>")
    browser.goto((tmp_path / "tall.html").as_uri())
    shot = browser.screenshot("tall.png")
    assert shot == tmp_path / "artifacts" / "tall.png" and png_size(shot) == (1280, 900)
    width = browser.evaluate("document.documentElement.scrollWidth")  # 1280 less the scroll bar
    assert png_size(browser.screenshot(tmp_path / "full.png", full_page=True)) == (width, 2000)


def test_no_binary_skips_with_the_install_command(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))
    monkeypatch.delenv("M3T_CHROMIUM", raising=False)
    assert find_chromium() is None
    with pytest.raises(pytest.skip.Exception, match=r"run `sudo apt-get install chromium` \(or bash "
                                                    r"\.ci/install-browser\)"):
        require_chromium()


# -- .ci/install-browser, run against stand-in id / sudo / apt-get on an otherwise empty PATH ----------------

FAKE_APT = """#!/bin/bash
echo "$DEBIAN_FRONTEND $*" >> "{log}"
case "$1" in
    update) : > "{state}/updated" ;;
    install)
        if [ "{mode}" = offline ]; then echo "E: Failed to fetch http://deb.debian.org/..."; exit 100; fi
        if [ "{mode}" = stale ] && [ ! -e "{state}/updated" ]; then
            echo "E: Unable to locate package chromium"; exit 100
        fi
        printf '#!/bin/bash\\necho "Chromium 150.0 stand-in"\\n' > "{bin}/chromium"
        chmod +x "{bin}/chromium" ;;
esac
"""


def run_installer(tmp_path: Path, *, uid: int, sudo: bool, apt: str | None, chromium: bool = False):
    """Run .ci/install-browser with PATH = a folder of stand-ins; returns (exit code, output, apt-get calls)."""
    bin_dir, state = tmp_path / "bin", tmp_path / "state"
    bin_dir.mkdir()
    state.mkdir()
    log = state / "apt.log"
    for tool in ("env", "chmod"):
        (bin_dir / tool).symlink_to(next(Path(d) / tool for d in ("/usr/bin", "/bin") if (Path(d) / tool).exists()))
    scripts = {"id": f'#!/bin/bash\necho {uid}\n'}
    if sudo:
        scripts["sudo"] = '#!/bin/bash\n[ "$1" = -n ] && shift\n"$@"\n'
    if apt:
        scripts["apt-get"] = FAKE_APT.format(log=log, state=state, mode=apt, bin=bin_dir)
    if chromium:
        scripts["chromium"] = "#!/bin/bash\necho Chromium\n"
    for name, text in scripts.items():
        (bin_dir / name).write_text(text)
        (bin_dir / name).chmod(0o755)
    done = subprocess.run(["/bin/bash", str(ROOT / ".ci" / "install-browser")], capture_output=True, text=True,
                          env={"PATH": str(bin_dir), "HOME": str(tmp_path)}, timeout=30)
    calls = log.read_text().splitlines() if log.exists() else []
    return done.returncode, done.stdout + done.stderr, calls


INSTALL = "noninteractive install -y -q chromium"


@pytest.mark.parametrize("case, uid, sudo, apt, chromium, calls, says", [
    ("present", 1000, False, "ok", True, [], "is there"),
    ("root", 0, False, "ok", False, [INSTALL], "Chromium 150.0 stand-in"),
    ("sudo", 1000, True, "ok", False, [INSTALL], "Chromium 150.0 stand-in"),
    ("stale lists", 0, False, "stale", False, [INSTALL, "noninteractive update -q", INSTALL], "stand-in"),
    ("offline", 0, False, "offline", False, [INSTALL], "apt-get install chromium failed here"),
    ("no rights", 1000, False, "ok", False, [], "run `sudo apt-get install chromium`"),
    ("no apt", 0, False, None, False, [], "run `sudo apt-get install chromium`"),
])
def test_install_browser_paths(tmp_path, case, uid, sudo, apt, chromium, calls, says):
    code, output, apt_calls = run_installer(tmp_path, uid=uid, sudo=sudo, apt=apt, chromium=chromium)
    assert code == 0, output  # a missing browser never fails the install
    assert apt_calls == calls, output
    assert says in output, output
    assert os.path.exists(tmp_path / "bin" / "chromium") == (chromium or case in ("root", "sudo", "stale lists"))
