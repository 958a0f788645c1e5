"""A picture of a report page, for documentation (the README's docs/report-*.png), and the
page checked in a real browser (`check_page`, what the tests run).

    python -m posecorr.analysis.screenshot REPORT.html OUT.png [--width 1280] [--height 2400]

Drives a headless Chromium when one is installed; the report itself never needs it.
"""
from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "chrome")


def find_browser() -> str | None:
    """The first headless-capable Chromium on PATH, or None."""
    return next((shutil.which(b) for b in BROWSERS if shutil.which(b)), None)


def _run(browser: str, args: list[str], profile: Path, timeout: float) -> subprocess.CompletedProcess:
    # --no-sandbox: Chromium refuses to run as root with its sandbox (CI containers); a fresh
    # profile directory: no state of another run (or of the user's browser) leaks in.
    return subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                           f"--user-data-dir={profile}", *args], check=True, capture_output=True, text=True,
                          timeout=timeout)


def screenshot(html_path: str | Path, png_path: str | Path, width: int = 1280, height: int = 2400) -> bool:
    """Screenshot a page with headless Chromium; False when no Chromium is installed or it fails."""
    browser = find_browser()
    if browser is None:
        return False
    png = Path(png_path).resolve()
    try:
        with tempfile.TemporaryDirectory(prefix="posecorr-chromium-") as profile:
            _run(browser, [f"--screenshot={png}", f"--window-size={int(width)},{int(height)}",
                           Path(html_path).resolve().as_uri()], Path(profile), 120)
    except (OSError, subprocess.SubprocessError):
        return False
    return png.exists() and png.stat().st_size > 0


# Injected first into a copy of the page: records every script error and console.error, and
# once the page has loaded writes what it found into the DOM, which --dump-dom prints.
_PROBE = """<script>
(function () {
  var errors = [];
  window.addEventListener("error", function (e) {
    var t = e.target;
    errors.push(t && t !== window && t.tagName ? "failed to load <" + t.tagName.toLowerCase() + ">"
                                              : String(e.message || e.type));
  }, true);
  var consoleError = console.error;
  console.error = function () { errors.push("console.error: " + Array.prototype.join.call(arguments, " "));
                                return consoleError.apply(console, arguments); };
  // A section's size, the widths of its first key-value list's columns, and the text that runs
  // past its edges (a table's scrolling box is a way to show a wide table, not text lost).
  function layout(section) {
    var box = section.getBoundingClientRect(), outside = [], range = document.createRange();
    var walker = document.createTreeWalker(section, NodeFilter.SHOW_TEXT);
    for (var node = walker.nextNode(); node; node = walker.nextNode()) {
      if (!node.textContent.trim() || node.parentElement.closest(".scroll")) continue;
      range.selectNodeContents(node);
      var r = range.getBoundingClientRect();
      if (r.width > 0 && (r.right > box.right + 0.5 || r.left < box.left - 0.5)) {
        outside.push(node.textContent.trim().slice(0, 80));
      }
    }
    var kv = section.querySelector("dl.kv");
    return {width: box.width, height: box.height, outside: outside,
            kv_columns: kv ? getComputedStyle(kv).gridTemplateColumns.split(" ").map(parseFloat) : null};
  }
  window.addEventListener("load", function () {
    var images = Array.prototype.map.call(document.images, function (img) {
      return {alt: img.alt, complete: img.complete, width: img.naturalWidth, height: img.naturalHeight};
    });
    var anchors = Array.prototype.map.call(document.querySelectorAll("nav a"), function (a) {
      var href = a.getAttribute("href") || "";
      return {href: href, resolves: href.charAt(0) === "#" && document.getElementById(href.slice(1)) !== null};
    });
    var sections = {};
    Array.prototype.forEach.call(document.querySelectorAll("section"), function (s) {
      sections[s.id] = layout(s);
    });
    var out = document.createElement("pre");
    out.id = "posecorr-browser-check";
    out.textContent = JSON.stringify({images: images, anchors: anchors, errors: errors, sections: sections});
    document.body.appendChild(out);
  });
})();
</script>"""
_RESULT = re.compile(r'<pre id="posecorr-browser-check">(.*?)</pre>', re.S)
_CONSOLE = re.compile(r"CONSOLE[^\]]*\]\s*(.*)")


def check_page(html_path: str | Path, work_dir: str | Path, timeout: float = 120, width: int = 1280) -> dict[str, Any]:
    """Load a report in headless Chromium, in a window `width` px wide, and say what the
    browser saw: {"images": [{alt, complete, width, height}], "anchors": [{href, resolves}]
    (the menu's), "errors": [script errors, failed loads, console.error calls], "sections":
    {id: {width, height (px), outside: [text running past the section's edges, outside a
    table's scrolling box], kv_columns: [px of each column of its first key-value list] or
    None}}, "console": [console lines Chromium logged]}.

    The page is copied into `work_dir` with a probe script in front (the report has no script
    of its own). Raises FileNotFoundError without a Chromium, RuntimeError when it fails or
    prints no result, subprocess.TimeoutExpired after `timeout` s.
    """
    browser = find_browser()
    if browser is None:
        raise FileNotFoundError(f"no headless Chromium on PATH ({', '.join(BROWSERS)})")
    work = Path(work_dir)
    page = Path(html_path).read_text(encoding="utf-8")
    head = page.find("<head>")
    if head < 0:
        raise RuntimeError(f"{html_path}: no <head> to put the probe in")
    probed = work / "probed.html"
    probed.write_text(page[:head + 6] + _PROBE + page[head + 6:], encoding="utf-8")
    profile = work / "chromium-profile"
    try:
        run = _run(browser, ["--enable-logging=stderr", "--v=0", "--virtual-time-budget=10000",
                             f"--window-size={int(width)},2400", "--dump-dom", probed.resolve().as_uri()],
                   profile, timeout)
    except subprocess.CalledProcessError as exc:
        raise RuntimeError(f"{browser} failed (exit {exc.returncode}): {exc.stderr.strip()[-600:]}") from None
    found = _RESULT.search(run.stdout)
    if found is None:
        raise RuntimeError(f"{browser} printed no result of the probe; stderr: {run.stderr.strip()[-600:]}")
    import html as html_text

    result = json.loads(html_text.unescape(found.group(1)))
    result["console"] = [m.group(1) for m in map(_CONSOLE.search, run.stderr.splitlines()) if m]
    return result


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
