"""Open an HTML view in headless Chromium and save a screenshot of it.

    python docs/scripts/screenshot_view.py logsph-trace-out/view.html docs/images/view.png

Chromium comes from the system's packages (Debian: ``apt install chromium``).
WebGL runs on the CPU (SwiftShader), and the page is given 15 s of virtual
time to draw. The network stays off: the view is self-contained, so what the
screenshot shows is what a user sees offline.
"""

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("html", type=Path)
    parser.add_argument("png", type=Path)
    parser.add_argument("--size", default="1200,800", help="window size, pixels (W,H)")
    args = parser.parse_args(argv)
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        sys.exit("no chromium on PATH (Debian: apt install chromium)")
    if not args.html.is_file():
        sys.exit(f"no such file: {args.html}")
    args.png.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as profile:
        command = [browser, "--headless", "--no-sandbox", "--disable-gpu",
                   "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                   "--disable-background-networking", "--disable-component-update",
                   "--disable-sync", "--disable-quic", "--no-first-run",
                   f"--user-data-dir={profile}", f"--window-size={args.size}",
                   "--virtual-time-budget=15000", f"--screenshot={args.png.resolve()}",
                   args.html.resolve().as_uri()]
        subprocess.run(command, check=True, timeout=180, capture_output=True)
    if not args.png.is_file() or args.png.stat().st_size < 10_000:
        sys.exit(f"chromium wrote no screenshot to {args.png}")
    print(f"wrote {args.png} ({args.png.stat().st_size:,} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
