"""docs/report-unregistered.png: the top of the page `examples/loop.sh` ends with (its step 2,
the proposal fitted), as headless Chromium draws it.

    python -m tools.report_screenshot [-o docs/report-unregistered.png]

The loop runs in a scratch folder with the checkout's posecorr first on PATH; the checkout is
not written but for the picture.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# The page's summary, metrics and workspace arrows: what the README and the loop guide show.
WIDTH, HEIGHT = 1280, 1850


def main(argv: list[str] | None = None) -> int:
    from posecorr.analysis.screenshot import screenshot

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=Path, default=ROOT / "docs" / "report-unregistered.png")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="posecorr-screenshot-") as scratch:
        env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
        subprocess.run(["bash", str(ROOT / "examples" / "loop.sh")], cwd=scratch, env=env, check=True,
                       stdout=subprocess.DEVNULL)
        if not screenshot(Path(scratch) / "step2.html", args.output, WIDTH, HEIGHT):
            print("no Chromium drew the page (Debian: apt install chromium)", file=sys.stderr)
            return 1
    print(f"-> {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
