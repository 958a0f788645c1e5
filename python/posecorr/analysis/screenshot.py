"""A picture of a report page, for documentation (the README's docs/report-*.png).

    python -m posecorr.analysis.screenshot REPORT.html OUT.png [--width 1280] [--height 2400]

Drives a headless Chromium when one is installed; the report itself never needs it.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "chrome")


def screenshot(html_path: str | Path, png_path: str | Path, width: int = 1280, height: int = 2400) -> bool:
    """Screenshot a page with headless Chromium; False when no Chromium is installed or it fails."""
    browser = next((shutil.which(b) for b in BROWSERS if shutil.which(b)), None)
    if browser is None:
        return False
    png = Path(png_path).resolve()
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
           f"--screenshot={png}", f"--window-size={int(width)},{int(height)}",
           Path(html_path).resolve().as_uri()]
    try:
        subprocess.run(cmd, check=True, capture_output=True, timeout=120)
    except (OSError, subprocess.SubprocessError):
        return False
    return png.exists() and png.stat().st_size > 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m posecorr.analysis.screenshot", description=__doc__.split("\n")[0])
    parser.add_argument("page", type=Path)
    parser.add_argument("output", type=Path)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=2400)
    args = parser.parse_args(argv)
    if not args.page.is_file():
        print(f"{args.page}: no such page", file=sys.stderr)
        return 2
    if not screenshot(args.page, args.output, args.width, args.height):
        print(f"{args.output}: not written (no headless Chromium on PATH: {', '.join(BROWSERS)}, or it failed)",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
