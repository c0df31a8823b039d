"""Look at the built site in a real browser: headless Chromium screenshots of some pages, served on localhost.

A page fails when the browser logs a console message (the site writes none), when any request it makes (an
image, a stylesheet, a script, the search index) is not answered 200, or when its screenshot is blank.

    python .ci/check_pages.py SITE_DIR OUT_DIR index.html tutorials/first-scene.html ...
"""

from __future__ import annotations

import functools
import http.server
import re
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync", "--hide-scrollbars",
         "--enable-logging=stderr", "--v=0", "--window-size=1280,1600"]


class Handler(http.server.SimpleHTTPRequestHandler):
    failed: list[str] = []

    def log_request(self, code="-", size="-"):
        if str(getattr(code, "value", code)) != "200":
            self.failed.append(f"{code} {self.path}")

    def log_message(self, *args):
        pass


def blank(png: Path) -> str | None:
    """Why the screenshot looks blank, or None: fewer than 2% of its pixels differ from its commonest colour,
    or it has fewer than 16 grey levels."""
    from PIL import Image

    img = Image.open(png).convert("L")
    hist = img.histogram()
    total = sum(hist)
    if total - max(hist) < 0.02 * total:
        return f"{(total - max(hist)) / total:.1%} of the pixels differ from the background"
    if sum(1 for h in hist if h) < 16:
        return f"only {sum(1 for h in hist if h)} grey levels"
    return None


def main(site: Path, out: Path, pages: list[str]) -> int:
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        print("check_pages: no chromium on PATH (apt-get install chromium)", file=sys.stderr)
        return 1
    out.mkdir(parents=True, exist_ok=True)
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(Handler, directory=str(site)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    problems = []
    try:
        for page in pages:
            Handler.failed = []
            shot = out / (page.replace("/", "_").removesuffix(".html") + ".png")
            with tempfile.TemporaryDirectory() as profile:
                proc = subprocess.run([chromium, *FLAGS, f"--user-data-dir={profile}", f"--screenshot={shot}",
                                       f"http://127.0.0.1:{server.server_port}/{page}"],
                                      capture_output=True, text=True, timeout=120)
            console = re.findall(r":CONSOLE[^\]]*\] (.*)", proc.stderr)
            why = [f"chromium exit {proc.returncode}"] if proc.returncode else []
            why += [f"console: {c}" for c in console] + [f"request: {f}" for f in Handler.failed]
            if not shot.is_file():
                why.append("no screenshot")
            elif (b := blank(shot)) is not None:
                why.append(f"blank screenshot: {b}")
            print(f"check_pages: {page}: {'; '.join(why) if why else 'ok'} ({shot})")
            problems += why
    finally:
        server.shutdown()
    return 1 if problems else 0


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    sys.exit(main(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3:]))
