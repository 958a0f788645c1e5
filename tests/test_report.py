"""The HTML report: one self-contained, parseable page with every section and the right content."""
from __future__ import annotations

import base64
import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from posecorr.data import PoseTable
from posecorr.analysis.interpretation import takeaway
from posecorr.analysis.page import N_WORST, SECTIONS, write_report
from posecorr.rotations import geodesic_angle, quat_to_matrix
from posecorr.simulate import simulate

DIAGNOSIS = {
    "candidates": [
        {"effect": "sweep", "rank": 1, "score": 40.0, "p_value": 1e-9, "cv_rmse_before": 2e-3,
         "cv_rmse_after": 1e-3, "present": True},
        {"effect": "drift", "rank": 2, "score": 0.5, "p_value": 0.4, "cv_rmse_before": 2e-3,
         "cv_rmse_after": 2e-3, "present": False},
    ],
    "features": [{"feature": "azimuth", "r2": 0.3}, {"feature": "t", "r2": 0.01}],
    "aliases": [["station", "mount"]],
    "model_effects": ["station", "mount"],
    "test": "likelihood ratio <script>",  # must come out escaped
    "some_future_key": {"nested": 1},
}
LEDGER = [
    {"time": "2024-01-01T00:00:00+00:00", "model": "a.onnx", "effects": [], "method": "pmc",
     "representation": "zhou", "cv": {"rmse_pos": 0.02, "rmse_rot": 0.05, "rmse_total": 0.07}},
    {"time": "2024-01-01T00:05:00+00:00", "model": "b_station.onnx", "effects": ["station", "mount"],
     "method": "pmc", "representation": "zhou", "test": {"rmse_pos": 0.001, "rmse_rot": 0.001,
                                                         "rmse_total": 0.002}},
]


class _Collector(HTMLParser):
    """Collects ids, img srcs, every src/href, and checks that tags nest."""

    VOID = {"img", "meta", "br", "hr", "link", "input"}

    def __init__(self) -> None:
        super().__init__()
        self.ids: list[str] = []
        self.imgs: list[str] = []
        self.urls: list[str] = []
        self.stack: list[str] = []
        self.errors: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if a.get("id"):
            self.ids.append(a["id"])
        if tag == "img":
            self.imgs.append(a.get("src") or "")
        for key in ("src", "href"):
            if a.get(key):
                self.urls.append(a[key])
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag: str) -> None:
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unbalanced </{tag}>, open: {self.stack[-3:]}")
        else:
            self.stack.pop()


def _parse(path: Path) -> tuple[str, _Collector]:
    text = path.read_text(encoding="utf-8")
    parser = _Collector()
    parser.feed(text)
    parser.close()
    assert not parser.errors, parser.errors[:3]
    assert parser.stack == [], parser.stack
    return text, parser


@pytest.fixture(scope="module")
def small() -> tuple[PoseTable, np.ndarray]:
    """120 Exp III poses and a 'correction' that is the reference plus small noise."""
    table = simulate(3, seed=0).table.subset(np.arange(120))
    rng = np.random.default_rng(1)
    corrected = table.reference.copy()
    corrected[:, :3] += rng.normal(0, 0.5e-3, size=(table.n, 3))
    dq = rng.normal(0, 0.4e-3, size=(table.n, 3))
    q = corrected[:, 3:7] + 0.5 * np.concatenate([np.zeros((table.n, 1)), dq], axis=1)
    corrected[:, 3:7] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return table, corrected


def test_full_report(tmp_path: Path, small: tuple[PoseTable, np.ndarray]) -> None:
    table, corrected = small
    info = {"file": "m<1>.onnx", "method": "pmc", "representation": "zhou", "effects": ["station", "mount"]}
    out = write_report(tmp_path / "r.html", table, corrected, info, DIAGNOSIS, LEDGER)
    text, parsed = _parse(out)

    for sid, _ in SECTIONS:
        assert sid in parsed.ids, sid
    # Every image is an embedded PNG; nothing is fetched from anywhere.
    # Figures: workspace, features (pos, rot), orientation, histograms, diagnosis R^2, ledger.
    assert len(parsed.imgs) == 7
    for src in parsed.imgs:
        assert src.startswith("data:image/png;base64,")
        assert base64.b64decode(src.split(",", 1)[1])[:8] == b"\x89PNG\r\n\x1a\n"
    assert all(u.startswith(("data:", "#")) for u in parsed.urls), [u for u in parsed.urls if u[:5] != "data:"]
    assert not re.search(r"""(src|href)\s*=\s*["']?\s*(https?:)?//""", text)
    assert "<script" not in text and "&lt;script&gt;" in text  # escaped, not executed
    assert "m&lt;1&gt;.onnx" in text

    # Header facts and the raw metric in mm.
    raw_pos_mm = 1e3 * np.sqrt(np.mean(np.sum((table.meas_p - table.ref_p) ** 2, axis=1)))
    assert f"{raw_pos_mm:.3g}" in text
    assert "full pose" in text and f"<dd>{table.n}</dd>" in text

    # Worst poses: computed independently, eq. 43 per pose (m + rad).
    dp = np.linalg.norm(corrected[:, :3] - table.ref_p, axis=1)
    dr = geodesic_angle(quat_to_matrix(table.ref_q), quat_to_matrix(corrected[:, 3:7]))
    worst = np.argsort(-(dp + dr))
    section = text[text.index('id="worst"'):text.index('id="diagnosis"')]
    rows = re.findall(r"<tr[^>]*><td[^>]*>(\d+)</td><td[^>]*>([^<]*)</td><td>(\d+)</td>", section)
    assert len(rows) == N_WORST
    assert [int(r[2]) for r in rows] == list(worst[:N_WORST])
    assert rows[0][1] == table.extras["id"][worst[0]]
    assert f"{dp[worst[0]] * 1e3:.3f}" in section

    # Diagnosis takeaway and table.
    assert "Most likely missing: sweep (present: yes, p &lt; 1e-6" in text
    assert "--effects station,mount,sweep" in text
    assert 'class="present"' in text and "station ≈ mount" in text

    # Ledger rows, both kinds of held-out block.
    ledger = text[text.index('id="ledger"'):]
    assert "b_station.onnx" in ledger and "station,mount" in ledger
    assert ">70.0<" in ledger and ">2.00<" in ledger  # rmse_total in mm + mrad


def test_position_only_small_no_time(tmp_path: Path) -> None:
    """Position-only, N < 15, no `t`, no model, no diagnosis, no ledger."""
    rng = np.random.default_rng(3)
    n = 9
    ref_p = np.column_stack([rng.uniform(-0.1, 0.1, n), rng.uniform(-0.7, -0.5, n), rng.uniform(0.4, 0.6, n)])
    q = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    table = PoseTable(ref_p + rng.normal(0, 0.01, (n, 3)), q, ref_p, None, {})
    corrected = np.concatenate([ref_p + rng.normal(0, 1e-3, (n, 3)), q], axis=1)
    out = write_report(tmp_path / "p.html", table, corrected)
    text, parsed = _parse(out)
    for sid, _ in SECTIONS:
        assert sid in parsed.ids, sid
    # Workspace, position features, orientation, histograms: no rotation, R^2 or ledger figure.
    assert len(parsed.imgs) == 4
    assert "position only" in text and "rot err [mrad]" not in text
    section = text[text.index('id="worst"'):text.index('id="diagnosis"')]
    assert len(re.findall(r"<tr[^>]*><td[^>]*>\d+</td>", section)) == n  # all poses, fewer than 15
    assert "ledger is empty" in text and "No diagnosis given" in text


def test_wrong_shape_rejected(tmp_path: Path, small: tuple[PoseTable, np.ndarray]) -> None:
    table, corrected = small
    with pytest.raises(ValueError, match="expected"):
        write_report(tmp_path / "x.html", table, corrected[:-1])


def test_takeaway_without_present_effect() -> None:
    diag = {"candidates": [{"effect": "drift", "rank": 1, "present": False}],
            "features": [{"feature": "yaw", "r2": 0.4}]}
    line = takeaway(diag, ["station"])
    assert "No catalogue effect is missing" in line and "yaw" in line
    assert takeaway({"candidates": [], "features": []}).startswith("No catalogue effect is missing")


def test_report_shows_the_still_segments_of_an_ingested_table(tmp_path) -> None:
    """Issue 15: a table from `posecorr ingest` has its segments beside it; the report lists
    them, rejected ones with their reason, and the clock offset."""
    import json as _json

    from posecorr.analysis.page import write_report
    from posecorr.ingest.pipeline import segments_path

    table = simulate(3, seed=0).table.subset(np.arange(4))
    sidecar = {"segments_found": 5, "segments_rejected": 1, "offset_s": 0.137, "offset_source": "estimated",
               "segments": [{"segment": i, "row": i, "status": "ok", "reason": None, "start_s": 10.0 * i,
                             "duration_s": 6.0, "kept_samples": 1400, "jitter_mm": 0.25} for i in range(4)]
               + [{"segment": 4, "row": None, "status": "rejected", "reason": "jitter 0.9 mm > 0.5 mm",
                   "start_s": 40.0, "duration_s": 6.0, "kept_samples": 1300, "jitter_mm": 0.9}]}
    data = tmp_path / "t.csv"
    segments_path(data).write_text(_json.dumps(sidecar))
    page = write_report(tmp_path / "r.html", table, table.reference,
                        segments=_json.loads(segments_path(data).read_text())).read_text()
    assert "5 still segments found, 1 rejected" in page
    assert "jitter 0.9 mm &gt; 0.5 mm" in page
    assert "+0.1370 s (estimated)" in page


def test_screenshot_drives_a_headless_chromium(tmp_path, monkeypatch) -> None:
    """The docs' pictures: a Chromium on PATH is called headless on the page's file URI and
    its PNG is reported written; without one (or when it fails) screenshot says False."""
    import stat

    from posecorr.analysis.screenshot import main, screenshot

    page = tmp_path / "r.html"
    page.write_text("<html></html>")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    monkeypatch.setenv("PATH", str(bin_dir))
    assert screenshot(page, tmp_path / "none.png") is False
    assert main([str(page), str(tmp_path / "none.png")]) == 1
    fake = bin_dir / "chromium"
    fake.write_text("#!/bin/sh\necho \"$@\" > \"$0.args\"\nfor a; do case $a in --screenshot=*) "
                    "printf PNG > \"${a#--screenshot=}\";; esac; done\n")
    fake.chmod(fake.stat().st_mode | stat.S_IXUSR)
    assert screenshot(page, tmp_path / "shot.png", width=800, height=600) is True
    assert (tmp_path / "shot.png").read_bytes() == b"PNG"
    args = (bin_dir / "chromium.args").read_text().split()
    assert "--headless" in args and "--window-size=800,600" in args and page.resolve().as_uri() in args
