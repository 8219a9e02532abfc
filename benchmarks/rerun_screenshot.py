"""Screenshot of a saved recording as a user sees it: Rerun's web viewer in headless Chromium.

Owns the picture of the default layout in the README (docs/images/rerun_layout.png): it opens
an .rrd in the web viewer with the blueprint the recording carries (viewer.blueprint) and
saves one PNG. Not part of the test suite (it needs Chromium and minutes of CPU rendering).

Run it (Debian's chromium and the playwright wheel; never ``playwright install``, which
downloads a browser of its own)::

    apt-get install -y chromium
    .venv/bin/pip install playwright
    .venv/bin/recon run ../shared/data/7scenes-redkitchen --max-frames 60 -o /tmp/shot_run --rerun save \\
        --stream on --poses estimate --quiet    # streamed, estimated: the cameras are logged once final
    .venv/bin/python benchmarks/rerun_screenshot.py /tmp/shot_run/recording.rrd   # -> docs/images/rerun_layout.png

How: the web viewer's files are served by the SDK (``rr.serve_web_viewer``) and the .rrd by a
small HTTP server on 127.0.0.1; the viewer opens ``?url=<the .rrd>``, so it loads the file with
its blueprint store exactly as ``rerun FILE.rrd`` would. Chromium renders WebGL with SwiftShader
(no GPU needed, slow: a 60-frame 7-Scenes run takes a few minutes on two cores). The page may
only talk to 127.0.0.1: every other request (the viewer's telemetry, fonts, update check) is
aborted and other host names do not resolve. The viewer has loaded the data when the file has
been sent and two screenshots taken ``--settle`` seconds apart are the same.
"""

from __future__ import annotations

import argparse
import socket
import sys
import threading
import time
from functools import partial
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import quote

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUTPUT = REPO / "docs" / "images" / "rerun_layout.png"
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
    # WebGL without a GPU: ANGLE on SwiftShader (a CPU Vulkan)
    "--use-gl=angle",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    # nothing but the local servers resolves
    "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
]
LOCAL = ("http://127.0.0.1:", "data:", "blob:")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _FileHandler(SimpleHTTPRequestHandler):
    """Serves one folder to the viewer's origin (another port, so CORS must allow it) and
    counts the requests answered in full."""

    done: list[str]

    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        super().end_headers()

    def do_GET(self) -> None:  # noqa: N802 (http.server's name)
        super().do_GET()
        self.done.append(self.path)

    def log_message(self, *args) -> None:
        pass


def _serve_file(path: Path) -> tuple[ThreadingHTTPServer, str, list[str]]:
    done: list[str] = []
    handler = partial(type("Handler", (_FileHandler,), {"done": done}), directory=str(path.parent))
    server = ThreadingHTTPServer(("127.0.0.1", _free_port()), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}/{quote(path.name)}", done


def _same(a: bytes, b: bytes) -> bool:
    import io

    import numpy as np
    from PIL import Image

    x, y = (np.asarray(Image.open(io.BytesIO(d)).convert("RGB"), dtype=np.int16) for d in (a, b))
    # a blinking cursor or a ticking label may differ; a view still loading differs a lot
    return x.shape == y.shape and float((np.abs(x - y).max(-1) > 8).mean()) < 1e-4


def screenshot(rrd: Path, output: Path, width: int = 1600, height: int = 1000, chromium: str = "/usr/bin/chromium",
               settle: float = 20.0, timeout: float = 900.0, log=partial(print, flush=True)) -> Path:
    """Open ``rrd`` in the web viewer in headless Chromium and save a width x height PNG."""
    import rerun as rr
    from playwright.sync_api import sync_playwright

    rrd = rrd.resolve()
    file_server, rrd_url, done = _serve_file(rrd)
    web_port = _free_port()
    rr.serve_web_viewer(web_port=web_port, open_browser=False)
    url = f"http://127.0.0.1:{web_port}/?url={quote(rrd_url, safe='')}"
    start = time.monotonic()
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_FLAGS, headless=True)
            page = browser.new_page(viewport={"width": width, "height": height})
            page.route("**/*", lambda route: route.continue_() if route.request.url.startswith(LOCAL)
                       else route.abort())
            page.goto(url)
            # Compiling the viewer's wasm alone takes a minute or more on a busy two-core machine.
            while not any(p.endswith(quote(rrd.name)) for p in done):
                if time.monotonic() - start > timeout:
                    raise TimeoutError(f"the viewer did not fetch {rrd_url} in {timeout:.0f} s")
                # not time.sleep: the sync API runs the route handler above only inside its own calls
                page.wait_for_timeout(1000)
            log(f"{time.monotonic() - start:.0f} s: {rrd.name} sent, waiting for the viewer to settle")
            # Software rendering takes many seconds per frame: a generous screenshot timeout.
            shot = page.screenshot(timeout=timeout * 1000)
            while True:
                page.wait_for_timeout(settle * 1000)
                previous, shot = shot, page.screenshot(timeout=timeout * 1000)
                if _same(previous, shot):
                    break
                log(f"{time.monotonic() - start:.0f} s: still changing")
                if time.monotonic() - start > timeout:
                    log(f"still changing after {timeout:.0f} s: keeping the last screenshot")
                    break
            browser.close()
    finally:
        file_server.shutdown()
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_bytes(shot)
    log(f"{time.monotonic() - start:.0f} s: wrote {output}")
    return output


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("rrd", type=Path, help="a saved recording (recon run --rerun save)")
    parser.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT, help="PNG to write (default: %(default)s)")
    parser.add_argument("--width", type=int, default=1600)
    parser.add_argument("--height", type=int, default=1000)
    parser.add_argument("--chromium", default="/usr/bin/chromium", help="browser executable (default: %(default)s)")
    parser.add_argument("--settle", type=float, default=20.0, help="seconds between the screenshots compared")
    parser.add_argument("--timeout", type=float, default=900.0, help="give up waiting after this many seconds")
    args = parser.parse_args(argv)
    if not args.rrd.is_file():
        parser.error(f"{args.rrd}: no such file")
    screenshot(args.rrd, args.output, args.width, args.height, args.chromium, args.settle, args.timeout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
