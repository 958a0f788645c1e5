"""The HTML report: one self-contained, parseable page with every section and the right content."""
from __future__ import annotations

import base64
import html
import json
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
    "aliases": [{"effects": ["station", "mount"], "correlation": 0.995},
                {"effects": ["sweep", "station"], "correlation": 0.996, "shared": 2, "of": 4}],
    "proposal": None,
    "no_proposal": "no form earns its place <b>",  # must come out escaped
    "model_effects": ["station", "mount"],
    "test": "likelihood ratio <script>",  # must come out escaped
    "some_future_key": {"nested": 1},
}
LEDGER = [
    {"time": "2024-01-01T00:00:00+00:00", "model": "a.onnx", "effects": [], "method": "pmc",
     "representation": "zhou", "cv": {"rmse_pos": 0.02, "rmse_rot": 0.05, "rmse_total": 0.07},
     "baseline": {"name": "rigid-joint", "rmse_pos": 0.004, "rmse_rot": 0.002, "rmse_total": 0.006}},
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
        if sid != "segments":
            assert sid in parsed.ids, sid
    # Not from `posecorr ingest`: no segments section, and no menu entry to one.
    assert "segments" not in parsed.ids and 'href="#segments"' not in text
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
    assert "<th>index</th>" in section and "made in memory, not read from a file" in section  # no file rows
    assert rows[0][1] == table.extras["id"][worst[0]]
    assert f"{dp[worst[0]] * 1e3:.3f}" in section

    # Diagnosis takeaway and table.
    assert "Most likely missing: sweep (present: yes, p &lt; 1e-6" in text
    assert "--effects station,mount,sweep" in text
    assert 'class="present"' in text and "cannot be told apart by this data: station ~ mount" in text
    assert "partly alike on these poses: sweep ~ station along 2 of 4 directions" in text

    # Ledger rows, both kinds of held-out block.
    ledger = text[text.index('id="ledger"'):]
    assert "b_station.onnx" in ledger and "station, mount" in ledger
    assert ">70.0<" in ledger and ">2.00<" in ledger  # rmse_total in mm + mrad
    # Against the rigid fit on the same poses where the line has it (6 / 70), else nothing.
    assert ">4.00 (joint)<" in ledger and ">0.0857×<" in ledger


def test_the_worst_pose_is_named_by_its_row_in_the_file(tmp_path: Path, capsys) -> None:
    """The worst-poses table named a pose by its 0-based index where every other message names
    the file's row: a pose whose measurement is 3 cm off, after blank lines (empty, spaces,
    only commas), is the worst and is named by the row an editor shows it on."""
    from posecorr.cli import main
    from posecorr.data import write_table
    from posecorr.train.pmc import PMC

    table = simulate(3, seed=0).table.subset(np.arange(80))
    model = tmp_path / "m.onnx"
    PMC(representation="zhou").fit(table.measured, table.reference).to_onnx(
        model, measured=table.measured, reference=table.reference)
    k = 50
    measured = table.measured
    toward = table.meas_p.mean(axis=0) - measured[k, :3]   # inside the model's box: toward the middle
    measured[k, :3] += 0.03 * toward / np.linalg.norm(toward)
    path = tmp_path / "d.csv"
    write_table(table.with_measured(measured), path)
    lines = path.read_text().splitlines()
    lines[30:30] = ["", "   ", "," * (len(lines[0].split(",")) - 1)]
    path.write_text("\n".join(lines) + "\n")
    assert lines[k + 1 + 3].startswith(f"{table.extras['id'][k]},")   # the pose, 3 lines further down

    assert main(["report", str(path), "--model", str(model), "-o", str(tmp_path / "r.html"), "--no-diagnosis"]) == 0
    text = (tmp_path / "r.html").read_text(encoding="utf-8")
    section = text[text.index('id="worst"'):text.index('id="diagnosis"')]
    assert "<th>row in d.csv</th>" in section and "the row of the file as an editor shows it" in section
    first = re.search(r"<tbody><tr><td[^>]*>1</td><td[^>]*>([^<]*)</td><td>(\d+)</td>", section)
    assert first is not None and first.group(1) == str(table.extras["id"][k])
    assert int(first.group(2)) == k + 2 + 3 and lines[int(first.group(2)) - 1] == lines[k + 1 + 3]


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
        assert sid in parsed.ids or sid == "segments", sid
    # Workspace, position features, orientation, histograms: no rotation, R^2 or ledger figure.
    assert len(parsed.imgs) == 4
    assert "position only" in text and "rot err [mrad]" not in text
    section = text[text.index('id="worst"'):text.index('id="diagnosis"')]
    assert len(re.findall(r"<tr[^>]*><td[^>]*>\d+</td>", section)) == n  # all poses, fewer than 15
    assert "ledger is empty" in text and "No diagnosis given" in text
    # the orientations shown are the measured ones (the table has none of the reference's):
    # the captions said "reference orientation"
    assert "Roll, pitch, yaw of the measured orientation" in text
    assert "the angles are of the measured orientation, in the tracker's frame" in html.unescape(section)
    assert "reference orientation relative to upright" not in text


def test_wrong_shape_rejected(tmp_path: Path, small: tuple[PoseTable, np.ndarray]) -> None:
    table, corrected = small
    with pytest.raises(ValueError, match="expected"):
        write_report(tmp_path / "x.html", table, corrected[:-1])


def test_the_history_names_a_representation_only_where_a_core_has_one(tmp_path, small) -> None:
    """A physics or rigid model's file carries the representation its graph computes in (R);
    the history shows it only for a method with a data-driven core (`METHODS`)."""
    table, corrected = small
    physics = {**LEDGER[0], "model": "c.onnx", "method": "physics", "representation": "R"}
    text, _ = _parse(write_report(tmp_path / "r.html", table, corrected, None, None, [LEDGER[0], physics]))
    section = text[text.index('id="ledger"'):]
    rows = re.findall(r"<tr[^>]*>(.*?)</tr>", section, flags=re.S)[1:3]
    cells = [re.findall(r"<td[^>]*>(.*?)</td>", row, flags=re.S) for row in rows]
    assert [row[4:6] for row in cells] == [["pmc", "zhou"], ["physics", "–"]], cells


def test_takeaway_without_present_effect() -> None:
    diag = {"candidates": [{"effect": "drift", "rank": 1, "present": False}],
            "features": [{"feature": "yaw", "r2": 0.4}]}
    line = takeaway(diag, ["station"])
    assert "No catalogue effect is missing" in line and "yaw" in line
    assert takeaway({"candidates": [], "features": []}).startswith("No catalogue effect is missing")
    # An effect that gains and fails the test is no "nothing is missing": the banner says which part.
    diag["absent"] = [{"effect": "drift", "score": 0.073, "p_value": 2e-6,
                       "why": "a fold where the error rises (worst fold -1.3%)"}]
    assert takeaway(diag, ["station"]) == (
        "No effect passes the test: drift lowers the held-out whitened error by 7.3% but is not present: "
        "a fold where the error rises (worst fold -1.3%). No form earns its place.")


def test_nothing_missing_keeps_to_what_the_poses_determine_and_names_the_best_by_kind() -> None:
    """On the real 11-pose session the diagnosis leaves a form undetermined and aliases effects
    with the registration: "no catalogue effect is missing" would claim more than the poses
    show, so the banner counts those it cannot judge. The best candidate is named by its kind
    (the proposal's words name the best form, which may be another), and among those the poses
    tell apart: the banner named range_scale "best" just after counting it among those they
    cannot tell from incidence."""
    diag = {"candidates": [{"effect": "range_scale", "kind": "effect", "rank": 1, "present": False},
                           {"effect": "strain", "kind": "form", "rank": 2, "present": False}],
            "features": [], "model_effects": ["station", "mount"],
            "aliases": [{"effects": ["station", "incidence"]}, {"effects": ["range_scale", "incidence"]}],
            "undetermined": [{"effect": "orientation_bias", "reason": "..."},
                             {"effect": "quadratic", "reason": "...", "in_model": "session_quadratic", "same": True}]}
    assert takeaway(diag, ["station", "mount"]) == (
        "No catalogue effect these poses can determine is missing (3 candidates they cannot determine or tell "
        "apart: orientation_bias, incidence, range_scale) and no form earns its place (best form: "
        "strain, not present); nothing tried explains what is left.")
    diag.update(aliases=[], undetermined=diag["undetermined"][1:], candidates=diag["candidates"][1:])
    assert takeaway(diag, ["station", "mount"]) == (
        "No catalogue effect is missing and no form earns its place (best form: strain, not present); "
        "nothing tried explains what is left.")


def test_where_no_candidate_could_pass_the_banner_says_the_poses_cannot_show_it(tmp_path) -> None:
    """The real 9-pose session 20200717_Exp2: its held-out residual leaves too few dimensions
    for any candidate's p to reach the threshold (chi2.sf of all of them on one degree of
    freedom, `score_test_reach`). The banner says so with those figures instead of "no
    catalogue effect is missing", which the test could not have shown."""
    from scipy.stats import chi2

    from posecorr.analysis.diagnose import diagnose
    from posecorr.data import read_table

    diagnosis = diagnose(read_table(Path(__file__).parent / "data" / "realdata" / "20200717_Exp2.csv"),
                         ["station", "mount"], folds=5, seed=0)
    reach = diagnosis["reach"]
    assert reach["can_pass"] is False and reach["best_p"] == pytest.approx(chi2.sf(reach["residual_dims"], 1))
    line = takeaway(diagnosis, ["station", "mount"])
    assert line.startswith(f"These 9 poses cannot show a missing effect: no candidate's p can fall below the test's "
                           f"threshold (at best {reach['best_p']:.2g} against {reach['threshold']:.2g})")
    assert "No catalogue effect is missing" not in line

    # The page of a model with a data-driven core says the diagnosis's base is its effects alone
    # (its "cv RMSE before" read as the model's); a physics-only model's page has no such words.
    table = read_table(Path(__file__).parent / "data" / "realdata" / "20200717_Exp2.csv")
    words = "its data-driven core (pmc-zhou) is not part of that base, so cv RMSE before is the effects' alone"
    for method, said in (("pmc", True), ("none", False)):
        info = {"method": method, "representation": "zhou", "effects": [{"name": "station"}, {"name": "mount"}]}
        page = write_report(tmp_path / f"{method}.html", table, table.reference, info, diagnosis)
        assert (words in html.unescape(page.read_text())) == said, method


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
    assert 'href="#segments"' in page and '<section id="segments">' in page
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


# --- the before: raw where the frames are registered, else the best rigid fit (issue 30, item 5) ---

def _metrics_rows(page: str) -> list[list[str]]:
    """The metrics table's body rows as lists of cell texts."""
    section = page[page.index('id="metrics"'):page.index('id="workspace"')]
    body = section[section.index("<tbody>"):section.index("</tbody>")]
    return [re.findall(r"<td[^>]*>(.*?)</td>", row) for row in re.findall(r"<tr[^>]*>(.*?)</tr>", body)]


def _rmse_pos(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :3] - b[:, :3]) ** 2, axis=1))))


def _kabsch_residuals(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """target - (R source + t) of the plain least-squares rigid fit (SVD, written out here)."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    u, _, vt = np.linalg.svd((source - cs).T @ (target - ct))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    R = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    return target - ((source - cs) @ R.T + ct)


@pytest.fixture(scope="module")
def unregistered() -> PoseTable:
    """40 poses in the tracker's own frame, metres from the reference frame (a session as real
    cells produce: any rotation, 1-4 m away, a lever arm, full orientations)."""
    from posecorr.simulate import simulate_session

    return simulate_session(0, n=40, spread="full", position_only=False, unremovable=0.0).table


def test_unregistered_frames_are_measured_against_the_rigid_fit(tmp_path: Path, unregistered: PoseTable) -> None:
    from posecorr.analysis.comparison import compare, rigid_label
    from posecorr.metrics import UNREGISTERED_FACTOR, UNREGISTERED_MIN_M

    table = unregistered
    rng = np.random.default_rng(5)
    corrected = table.reference.copy()
    corrected[:, :3] += rng.normal(0, 0.1e-3, (table.n, 3))
    kabsch = _kabsch_residuals(table.meas_p, table.ref_p)
    kabsch_rmse = float(np.sqrt(np.mean(np.sum(kabsch ** 2, axis=1))))
    raw = _rmse_pos(table.measured, table.reference)
    assert raw > 0.5 and kabsch_rmse < 0.05           # the premise: metres apart, centimetres after a rigid fit

    comparison = compare(table, corrected)
    summary = comparison.to_json()
    baseline = summary["baseline"]
    assert comparison.unregistered and raw > max(UNREGISTERED_FACTOR * baseline["rmse_pos"], UNREGISTERED_MIN_M)
    assert baseline["name"].startswith("rigid-") and comparison.baseline == rigid_label(baseline["name"])
    # The best rigid fit is no worse than the plain Kabsch fit (one of its variants; the others
    # add the 2-8 cm lever arm), and the before poses are its residuals.
    assert baseline["rmse_pos"] <= kabsch_rmse * (1 + 1e-9)
    assert _rmse_pos(comparison.before, table.reference) == pytest.approx(baseline["rmse_pos"], rel=1e-9)
    # Another rigid change of the tracker's frame (2 rad, metres) does not move the rigid fit's residual.
    from posecorr.rotations import matrix_to_quat, rotvec_to_matrix

    W = rotvec_to_matrix(np.array([0.3, -1.2, 1.5]))
    moved = np.concatenate([table.meas_p @ W.T + [3.0, -2.0, 1.0],
                            matrix_to_quat(W @ quat_to_matrix(table.meas_q))], axis=1)
    assert compare(table.with_measured(moved), corrected).rigid["rmse_pos"] == pytest.approx(baseline["rmse_pos"],
                                                                                             rel=1e-4)
    after = _rmse_pos(corrected, table.reference)
    assert summary["after"]["rmse_pos"] == pytest.approx(after, rel=1e-9)
    assert summary["improvement"]["pos"] == pytest.approx(baseline["rmse_pos"] / after, rel=1e-9)
    assert summary["after"]["scored"] == "in-sample"

    # The arrows: scaled to the rigid fit's residuals, not to the metres of raw.
    before_p95_mm = 1e3 * np.percentile(np.linalg.norm(comparison.before[:, :3] - table.ref_p, axis=1), 95)
    raw_p95_mm = 1e3 * np.percentile(np.linalg.norm(table.meas_p - table.ref_p, axis=1), 95)
    key = summary["arrows"]["before_key_mm"]
    assert 1 / 1.6 < key / before_p95_mm < 1.6                 # the 1-2-5 step nearest the typical arrow
    assert key < raw_p95_mm / 100

    page = write_report(tmp_path / "u.html", table, corrected, comparison=comparison).read_text()
    rows = _metrics_rows(page)
    assert rows[0][0] == f"before: {rigid_label(baseline['name'])}" and rows[0][1] == "in-sample"
    assert rows[1][0] == "corrected (model)" and rows[1][1] == "in-sample"
    assert rows[0][2] == f"{1e3 * baseline['rmse_pos']:#.3g}".rstrip(".")
    assert rows[2][0].startswith(f"improvement ({rigid_label(baseline['name'])} / corrected)")
    assert not any("raw" in row[0] for row in rows)                # raw is no before here...
    assert f"{1e3 * raw:.3g}" in page and "10× the best rigid fit" in page   # ...only the rule and its figure
    assert f'data-before-key-mm="{key:g}"' in page
    assert "rigid pos [mm]" in page[page.index('id="worst"'):]
    # where the station stands in these frames nobody knows: no feature is taken from it
    from posecorr.analysis.features import STATION_FEATURES, UNPLACED_STATION

    worst = page[page.index('id="worst"'):page.index('id="diagnosis"')]
    assert "yaw [deg]" in worst and not any(f"{name} [" in worst for name in STATION_FEATURES)
    assert UNPLACED_STATION in page.replace("&#x27;", "'")


def test_registered_frames_keep_raw_as_the_before(tmp_path: Path, small: tuple[PoseTable, np.ndarray]) -> None:
    from posecorr.analysis.comparison import compare

    table, corrected = small
    summary = compare(table, corrected).to_json()
    raw = _rmse_pos(table.measured, table.reference)
    # The paper's Exp III: raw holds a station registration error of cm, 20x the rigid fit's
    # residual; the frames are registered all the same.
    assert raw > 10 * summary["rigid_fit"]["rmse_pos"]
    assert summary["unregistered"] is False
    assert summary["baseline"]["name"] == "raw"
    assert summary["baseline"]["rmse_pos"] == pytest.approx(raw, rel=1e-9)
    assert summary["improvement"]["pos"] == pytest.approx(raw / _rmse_pos(corrected, table.reference), rel=1e-9)
    page = write_report(tmp_path / "r.html", table, corrected).read_text()
    rows = _metrics_rows(page)
    assert rows[0][0] == "raw (measured)" and rows[1][1] == "in-sample"
    assert rows[2][0].startswith("improvement (raw / corrected)")


def _cli(*args: str, cwd: Path) -> dict:
    import json
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "posecorr.cli", *args, "--json"], capture_output=True, text=True,
                         timeout=600, cwd=cwd)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


def test_the_history_holds_the_fits_of_this_table_only(tmp_path: Path) -> None:
    """A session simulated into the name of another, its ledger still beside it: the page's
    history showed the first table's fits as this one's. They are left out, and said so."""
    import subprocess
    import sys

    from posecorr.analysis.ledger import read_ledger
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    data = tmp_path / "s.csv"
    for seed, model in ((1, "first.onnx"), (2, "second.onnx")):
        write_table(simulate_session(seed, n=20, spread="full", position_only=False, unremovable=0.0).table, data)
        _cli("fit", str(data), "-o", model, "--effects", "station,mount", "--method", "none", "--cv", "5",
             cwd=tmp_path)
    assert [r["model"] for r in read_ledger(data)] == ["first.onnx", "second.onnx"]
    run = subprocess.run([sys.executable, "-m", "posecorr.cli", "report", str(data), "--model", "second.onnx",
                          "-o", "r.html", "--no-diagnosis"], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert "s.csv.ledger.jsonl: 1 fit of another table under this name" in run.stderr, run.stderr
    history = (tmp_path / "r.html").read_text().split('id="ledger"')[1]
    assert "second.onnx" in history and "first.onnx" not in history


@pytest.mark.parametrize("cv", ["5", "none"])
def test_held_out_where_the_ledger_knows_the_folds_in_sample_otherwise(tmp_path: Path, cv: str) -> None:
    """A fit writes the ledger line; the report rebuilds the model's and the rigid fit's
    held-out predictions from it (5 folds; a test split on 120 poses) and says so in the
    table; without the ledger, or for another table, the same model is in-sample."""
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session
    from posecorr.train.splits import split_indices

    n = 40 if cv == "5" else 120
    table = simulate_session(1, n=n, spread="full", position_only=False, unremovable=0.0).table
    data = tmp_path / "s.csv"
    write_table(table, data)
    fitted = _cli("fit", str(data), "-o", "m.onnx", "--effects", "station,mount", "--method", "none",
                  "--cv", cv, cwd=tmp_path)
    kind = "cv" if cv == "5" else "test"
    report = _cli("report", str(data), "--model", "m.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    after = report["after"]
    assert after["held_out"] is True
    # The report's held-out figures are the fit's: rebuilt on the same folds (float64), or the
    # model file on the same test poses (float32 graph, the same C runtime as fit's scoring).
    tolerance = 1e-6 if cv == "5" else 1e-4
    assert after["rmse_pos"] == pytest.approx(fitted[kind]["rmse_pos"], rel=tolerance)
    # the ledger's own figures beside them, and no improvement against raw (frames unregistered)
    assert report["unregistered"] is True
    assert after["ledger"] == pytest.approx({k: fitted[kind][k] for k in ("rmse_pos", "rmse_rot", "rmse_total")})
    assert "improvement" not in json.dumps(after)
    assert report["baseline"]["name"] == fitted["baseline"]["name"] == report["rigid_fit"]["name"]
    assert report["baseline"]["rmse_pos"] == pytest.approx(fitted["baseline"]["rmse_pos"], rel=1e-6)
    if cv == "5":
        assert after["n"] == n and after["scored"] == f"held-out (5 folds, {n} poses)"
    else:
        test_rows = split_indices(n, 0)[2]
        assert after["n"] == len(test_rows) and after["scored"] == f"held-out (test split, {len(test_rows)} poses)"
    page = (tmp_path / "r.html").read_text()
    rows = _metrics_rows(page)
    assert rows[1][1] == after["scored"] and rows[0][1] == after["scored"]
    # the figures the file states of itself, in fit's layout ({kind: figures, "raw": ...})
    stated = ", cross-validated" if cv == "5" else " on its test split"
    assert f"From its metadata, the model's own held-out figures{stated}: rmse_pos" in page

    # The table recorded again into the same file (20 references moved 20 mm), its ledger
    # line still beside it: the fit's held-out figures were rebuilt on the new poses and shown
    # as the model's. Now: the model file on poses it was not fitted on, said so.
    from posecorr.controller.apply import apply_file

    moved = table.subset(np.arange(n))
    moved.ref_p = moved.ref_p.copy()
    moved.ref_p[:20, 0] += 0.02
    write_table(moved, data)
    report = _cli("report", str(data), "--model", "m.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    assert report["after"]["held_out"] is False and report["after"]["scored"] == "not the fit's table"
    assert "neither the model's training_data_digest nor its fitted_table_digest" in report["after"]["reason"]
    applied = apply_file(tmp_path / "m.onnx", data, tmp_path / "a.csv", backend="c")
    assert applied["in_sample"] is False
    assert report["after"]["rmse_pos"] == pytest.approx(applied["corrected"]["rmse_pos"], rel=1e-6)
    write_table(table, data)

    # The same model without its ledger line: in-sample (a test split's table: mostly), said in
    # the table.
    (tmp_path / "s.csv.ledger.jsonl").unlink()
    report = _cli("report", str(data), "--model", "m.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    scored = "in-sample" if cv == "5" else "the fit's table, mostly in-sample"
    assert report["after"]["held_out"] is False and report["after"]["scored"] == scored
    assert "no ledger line" in report["after"]["reason"]
    assert report["after"]["n"] == n
    rows = _metrics_rows((tmp_path / "r.html").read_text())
    assert rows[0][1] == "in-sample" and html.unescape(rows[1][1]) == scored


def _compared(data: Path, model: Path):
    """The report's `Comparison` of the table at `data` against `model`, with the ledger line
    beside the table (the Python API under `posecorr report`)."""
    from posecorr.analysis.comparison import compare
    from posecorr.analysis.ledger import entry_for_model, read_ledger
    from posecorr.controller.apply import correct_table
    from posecorr.controller.onnx_meta import read_info
    from posecorr.controller.runtime import Corrector
    from posecorr.data import read_table

    table = read_table(data)
    corrected = correct_table(Corrector(model), model, table)
    return table, compare(table, corrected, entry_for_model(read_ledger(data), model), model_info=read_info(model))


@pytest.mark.parametrize("cv", ["loo", "5", "none"])
def test_the_fits_poses_in_another_order_are_held_out_on_its_folds(tmp_path: Path, cv: str) -> None:
    """The fit's table shuffled in place (a spreadsheet's sort): the report called it "not the
    fit's table" and lost the held-out figures. Its rows are put back in the fit's order (the
    ledger's row_ranks): the same folds, the same figures, each pose still the table's own row.
    A shuffled copy without the ledger, or with an older ledger line, is the fit's poses
    in-sample, said so."""
    from posecorr.analysis.ledger import of_table, read_ledger
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    n = 40 if cv != "none" else 120
    table = simulate_session(1, n=n, spread="full", position_only=False, unremovable=0.0).table
    data, model = tmp_path / "s.csv", tmp_path / "m.onnx"
    write_table(table, data)
    _cli("fit", str(data), "-o", str(model), "--effects", "station,mount", "--method", "none", "--cv", cv,
         cwd=tmp_path)
    original = _cli("report", str(data), "--model", str(model), "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    assert original["after"]["held_out"] is True
    shuffle = np.random.default_rng(7).permutation(n)
    write_table(table.subset(shuffle), data)
    shuffled = _cli("report", str(data), "--model", str(model), "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    assert shuffled["after"]["held_out"] is True and shuffled["after"]["scored"] == original["after"]["scored"]
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        assert shuffled["after"][key] == pytest.approx(original["after"][key], rel=1e-9), key
    for key in ("rmse_pos", "rmse_rot"):
        assert shuffled["baseline"][key] == pytest.approx(original["baseline"][key], rel=1e-9), key
    # each figure is of the shuffled table's own row: row `shuffle[i]` of the fit's is its row i
    read, comparison = _compared(data, model)
    _, fit_order = _compared_in_order(tmp_path, table, model)
    np.testing.assert_array_equal(shuffle[comparison.rows], fit_order.rows)
    assert of_table(read_ledger(data), read)[1] == 0   # the fit is in this table's history

    copy = tmp_path / "copy.csv"
    write_table(table.subset(shuffle), copy)
    label = "the fit's poses in another order, in-sample" if cv != "none" else \
        "the fit's table in another order, mostly in-sample"
    without = _cli("report", str(copy), "--model", str(model), "-o", "c.html", "--no-diagnosis", cwd=tmp_path)
    assert without["after"]["held_out"] is False and without["after"]["scored"] == label
    assert "in another order" in without["after"]["reason"] and "no ledger line" in without["after"]["reason"]
    lines = [json.loads(line) for line in (tmp_path / "s.csv.ledger.jsonl").read_text().splitlines()]
    (tmp_path / "copy.csv.ledger.jsonl").write_text(
        "".join(json.dumps({k: v for k, v in line.items() if k != "row_ranks"}) + "\n" for line in lines))
    older = _cli("report", str(copy), "--model", str(model), "-o", "c.html", "--no-diagnosis", cwd=tmp_path)
    assert older["after"]["held_out"] is False and older["after"]["scored"] == label
    assert "no row_ranks" in older["after"]["reason"]


def _compared_in_order(tmp_path: Path, table: PoseTable, model: Path):
    """`_compared` of `table` as the fit read it, its ledger line beside it."""
    from posecorr.data import write_table

    data = tmp_path / "in_order.csv"
    write_table(table, data)
    (tmp_path / "in_order.csv.ledger.jsonl").write_text((tmp_path / "s.csv.ledger.jsonl").read_text())
    return _compared(data, model)


def test_a_model_without_the_digest_of_any_order_says_only_what_it_knows() -> None:
    """A model exported before training_set_digest cannot tell its poses reversed from other
    poses: "not the fit's table" would be false of them, "in its order" is true of both."""
    from posecorr.analysis.comparison import compare
    from posecorr.controller.digest import data_digest, set_digest
    from posecorr.simulate import simulate_session

    table = simulate_session(1, n=20).table
    reversed_table = table.subset(np.arange(table.n)[::-1])
    older = {"training_data_digest": data_digest(table.measured, table.reference)}
    comparison = compare(reversed_table, reversed_table.measured, model_info=older)
    assert comparison.scored == "not the fit's table in its order" and not comparison.held_out
    assert "cannot tell them in another order from other poses" in comparison.reason
    newer = {**older, "training_set_digest": set_digest(table.measured, table.reference)}
    comparison = compare(reversed_table, reversed_table.measured, model_info=newer)
    assert comparison.scored == "the fit's poses in another order, in-sample"
    moved = table.subset(np.arange(table.n))
    moved.ref_p = moved.ref_p + 1e-9
    assert compare(moved, moved.measured, model_info=newer).scored == "not the fit's table"


def test_identical_rows_are_interchangeable_in_the_fits_order(tmp_path: Path) -> None:
    """Two rows of the same pose (a robot sent to one pose twice, a row pasted twice): the table
    shuffled puts either copy in either place, and each row of the table is still scored once,
    on the fit's folds."""
    from posecorr.controller.digest import set_digest
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    n = 40
    table = simulate_session(1, n=n, spread="full", position_only=False, unremovable=0.0).table
    twice = np.arange(n)
    twice[17] = 3
    table = table.subset(twice)
    data, model = tmp_path / "s.csv", tmp_path / "m.onnx"
    write_table(table, data)
    _cli("fit", str(data), "-o", str(model), "--effects", "station,mount", "--method", "none", "--cv", "5",
         cwd=tmp_path)
    first, original = _compared(data, model)
    assert original.held_out is True
    # the shuffle puts the second copy before the first
    shuffle = np.random.default_rng(3).permutation(n)
    assert list(shuffle).index(17) < list(shuffle).index(3)
    swapped = table.subset(shuffle)
    assert set_digest(swapped.measured, swapped.reference) == set_digest(table.measured, table.reference)
    write_table(swapped, data)
    read, comparison = _compared(data, model)
    assert comparison.held_out is True and comparison.scored == original.scored
    assert sorted(comparison.rows) == list(range(n))   # no row taken twice, none left out
    np.testing.assert_array_equal(read.measured[comparison.rows], first.measured[original.rows])
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        assert comparison.after_metrics[key] == pytest.approx(original.after_metrics[key], rel=1e-9), key


def test_report_json_carries_the_held_parameters_as_fit_does(tmp_path: Path) -> None:
    """The page showed the parameters a fit held (not determined) and fit --json and info
    --json carried them as `fixed`; report --json had no such key."""
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    write_table(simulate_session(1, n=12).table, tmp_path / "s.csv")   # too few for physics: Kabsch, no lever
    fitted = _cli("fit", "s.csv", "-o", "m.onnx", "--effects", "station,mount", "--method", "none", cwd=tmp_path)
    assert fitted["fixed"], fitted["chosen"]
    report = _cli("report", "s.csv", "--model", "m.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    assert report["fixed"] == fitted["fixed"] == _cli("info", "m.onnx", cwd=tmp_path)["fixed"]
    write_table(simulate_session(1, n=40, spread="full", position_only=False).table, tmp_path / "t.csv")
    fitted = _cli("fit", "t.csv", "-o", "n.onnx", "--effects", "station,mount", "--method", "none", cwd=tmp_path)
    report = _cli("report", "t.csv", "--model", "n.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    assert report["fixed"] == fitted["fixed"] == {}


def test_auto_is_held_out_as_fit_scored_it(tmp_path: Path) -> None:
    """`--method auto` scores each fold by the candidate an inner cross-validation chooses on
    its training poses; the report rebuilds those predictions and gets fit's figure."""
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    # a range scale beyond the registration: a core earns its place, so auto takes the nested path
    table = simulate_session(2, n=30, spread="full", position_only=False, unremovable=0.0,
                             extra={"range_scale": np.array([0.01])}).table
    data = tmp_path / "s.csv"
    write_table(table, data)
    fitted = _cli("fit", str(data), "-o", "m.onnx", "--effects", "station,mount", "--method", "auto",
                  "--cv", "5", cwd=tmp_path)
    assert not fitted["chosen"].startswith("rigid"), fitted["chosen"]    # the nested path, not a rigid one
    report = _cli("report", str(data), "--model", "m.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    after = report["after"]
    assert after["held_out"] is True and after["scored"] == "held-out (5 folds, 30 poses)"
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        assert after[key] == pytest.approx(fitted["cv"][key], rel=1e-6)
    assert report["baseline"]["rmse_pos"] == pytest.approx(fitted["baseline"]["rmse_pos"], rel=1e-6)



def test_a_position_only_fit_is_rebuilt_as_fit_made_it(tmp_path: Path) -> None:
    """On a table without reference orientations `fit` puts its core in position only; the
    report rebuilt the ledger's spec as written (zhou) and scored another model: 0.595 mm
    against fit's 0.581, an improvement over the rigid fit turned into a loss."""
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    table = simulate_session(407, n=60, robot="", spread="yaw", position_only=True, unremovable=0.0,
                             extra={"range_scale": np.array([0.01])}).table
    assert not table.has_orientation
    data = tmp_path / "s.csv"
    write_table(table, data)
    fitted = _cli("fit", str(data), "-o", "m.onnx", "--effects", "station,mount", "--method", "pmc", "--cv", "5",
                  cwd=tmp_path)
    report = _cli("report", str(data), "--model", "m.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    assert report["after"]["held_out"] is True
    assert report["after"]["rmse_pos"] == pytest.approx(fitted["cv"]["rmse_pos"], rel=1e-6), (report["after"], fitted["cv"])

def test_too_few_poses_for_a_diagnosis_still_give_the_page_and_say_why(tmp_path: Path) -> None:
    """Four poses: the default 5-fold diagnosis cannot run, the page is written without it and
    says why and which folds can (a fold of 4 leaves 3 to fit on, the fewest a fit takes); the
    folds it names do diagnose the table. Three poses (the model fitted on four): no folds can,
    it names the rows a diagnosis takes and the folds for them."""
    from posecorr.analysis.diagnose import diagnose
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session
    from posecorr.train.splits import MIN_FIT_POSES

    table = simulate_session(3, n=6, spread="full", position_only=False, unremovable=0.0).table
    write_table(table.subset(np.arange(4)), tmp_path / "fit.csv")
    _cli("fit", "fit.csv", "-o", "m.onnx", "--effects", "station", "--method", "none", cwd=tmp_path)
    for n, why in ((4, "4 rows, but a 5-fold diagnosis needs at least 5: fewer folds (--cv 4)"),
                   (3, f"3 rows, but a diagnosis takes at least {MIN_FIT_POSES + 1} (with --cv {MIN_FIT_POSES + 1})")):
        data = tmp_path / f"s{n}.csv"
        write_table(table.subset(np.arange(n)), data)
        report = _cli("report", str(data), "--model", "m.onnx", "-o", f"r{n}.html", cwd=tmp_path)
        assert report["diagnosis"] is None and report["no_diagnosis"] == why
        page, _ = _parse(tmp_path / f"r{n}.html")
        assert f"No diagnosis: {why}." in page
    result = diagnose(table.subset(np.arange(4)), ["station"], folds=4)
    assert result["folds"] == 4 and result["rows"]["used"] == 4


def test_the_history_plot_draws_each_fit_against_the_rigid_fit() -> None:
    """The loop's history: each ledger line's held-out rmse_pos, and the rigid fit on the
    same poses as a line where the ledger line has it (older lines: none)."""
    from posecorr.analysis.figures import ledger_figure

    fig = ledger_figure(LEDGER)
    lines = {line.get_label(): line for line in fig.axes[0].get_lines()}
    model = lines["model, held-out"]
    assert np.allclose(model.get_ydata(), [20.0, 1.0])
    rigid = np.asarray(lines["best rigid fit, same poses"].get_ydata(), float)
    assert rigid[0] == pytest.approx(4.0) and np.isnan(rigid[1])
    assert fig.axes[0].get_ylabel() == "held-out rmse_pos [mm]"


def _long_history() -> list[dict]:
    """Seven fits of one session, as the loop's ledger has them after a few more tries."""
    steps = [["station", "mount"], ["station", "mount", "session_strain"], ["station", "mount"],
             ["station", "mount", "session_strain", "sweep"], ["station"],
             ["station", "mount", "session_strain", "range_scale"], ["station", "mount", "session_strain"]]
    return [{"effects": effects, "method": "none", "plan": "loo", "cv": {"rmse_pos": pos * 1e-3},
             "baseline": {"rmse_pos": 6.4e-3}} for effects, pos in zip(steps, (6.45, 0.79, 2.05, 0.83, 6.55, 0.79, 0.8))]


def test_a_long_history_s_labels_stand_apart() -> None:
    """Seven fits: '5: -mount,session_strain,sweep' ran into '6: +mount,session_strain,range_scale';
    a label is broken after its commas to its fit's share of the axis."""
    from posecorr.analysis.figures import ledger_figure

    fig = ledger_figure(_long_history())
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    labels = fig.axes[0].get_xticklabels()
    assert labels[4].get_text() == "5: -mount,session_strain,\nsweep\nnone, leave one out"
    boxes = [t.get_window_extent(renderer) for t in labels]
    for k, (left, right) in enumerate(zip(boxes, boxes[1:])):
        assert left.x1 < right.x0, (labels[k].get_text(), labels[k + 1].get_text())


def _legends_over_data(fig: object) -> list[str]:
    """Every legend of a drawn figure that covers a bar, a line, a set of markers or a value
    label of a panel (each as drawn, clipped to its panel), or runs past the figure's edge."""
    from matplotlib.transforms import Bbox

    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    legends = [lg for lg in [*fig.legends, *(ax.get_legend() for ax in fig.axes)] if lg is not None]
    assert legends
    found = []
    for legend in legends:
        box = legend.get_window_extent(renderer)
        name = legend.get_texts()[0].get_text()
        if box.x0 < fig.bbox.x0 or box.y0 < fig.bbox.y0 or box.x1 > fig.bbox.x1 or box.y1 > fig.bbox.y1:
            found.append(f"{name}: past the figure's edge")
        for ax in fig.axes:
            for artist in [*ax.patches, *ax.get_lines(), *ax.collections, *ax.texts]:
                drawn = Bbox.intersection(artist.get_window_extent(renderer), ax.bbox)
                if drawn is not None and drawn.width * drawn.height > 0 and box.overlaps(drawn):
                    found.append(f"{name}: over {type(artist).__name__} {artist.get_label()!r}")
    return found


def test_no_legend_covers_what_it_describes() -> None:
    """The history's legend stood in the upper right over the rigid fit's line, the histograms'
    in the upper left over the tallest bars (the loop's page, the real sessions'): a legend
    stands beside its data, on short and long histories, one or two histogram panels, bars to
    either side, and feature panels with and without a spare panel for it."""
    from posecorr.analysis.figures import features_figure, histogram_figure, ledger_figure

    rng = np.random.default_rng(2)
    history = _long_history()
    same = np.array([2.0] * 6 + [3.0, 5.0, 9.0, 20.0, 40.0])  # a rigid model's: one histogram, tallest bar left
    figures = {"history of 2": ledger_figure(LEDGER), "history of 7": ledger_figure(history),
               "history of 1": ledger_figure(history[:1]),
               "histograms": histogram_figure((rng.lognormal(1.8, 0.3, 50), rng.lognormal(-0.4, 0.5, 50)),
                                              (rng.lognormal(-0.2, 0.4, 50), rng.lognormal(-0.2, 0.4, 50))),
               "one histogram": histogram_figure((same, same), None)}
    for n in (4, 6):  # a full grid, and one with a spare panel
        features = {name: rng.uniform(0, 1, 30) for name in ("x", "y", "z", "roll", "pitch", "yaw")[:n]}
        figures[f"{n} feature panels"] = features_figure(features, rng.uniform(1, 9, 30), rng.uniform(0.1, 1, 30),
                                                         "position error", "mm")
    for name, fig in figures.items():
        assert not _legends_over_data(fig), (name, _legends_over_data(fig))


def _history_rows(page: str) -> list[list[str]]:
    """The history table's body rows as lists of cell texts."""
    section = page[page.index('id="ledger"'):]
    body = section[section.index("<tbody>"):section.index("</tbody>")]
    return [re.findall(r"<td[^>]*>(.*?)</td>", row, flags=re.S) for row in re.findall(r"<tr[^>]*>(.*?)</tr>", body)]


def test_the_history_names_a_held_out_plan_as_the_metrics_table_does(tmp_path: Path) -> None:
    """A --cv loo fit: the metrics table said "held-out (leave one out, 12 poses)", the history's
    held-out column and its plot's labels said "cv". Now both name the plan in the table's
    words (leave one out, 3 folds); a line of an older posecorr, without its plan, by its
    block: cross-validated or test split."""
    from posecorr.analysis.figures import ledger_figure
    from posecorr.analysis.ledger import read_ledger
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    write_table(simulate_session(1, n=12, spread="full", position_only=False).table, tmp_path / "s.csv")
    for cv in ("3", "loo"):
        _cli("fit", "s.csv", "-o", f"m{cv}.onnx", "--effects", "station,mount", "--method", "none", "--cv", cv,
             cwd=tmp_path)
    report = _cli("report", "s.csv", "--model", "mloo.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    assert report["after"]["scored"] == "held-out (leave one out, 12 poses)"
    page = (tmp_path / "r.html").read_text()
    assert _metrics_rows(page)[1][1] == report["after"]["scored"]
    assert [row[6] for row in _history_rows(page)] == ["3 folds", "leave one out"]
    ledger = read_ledger(tmp_path / "s.csv")
    labels = [t.get_text() for t in ledger_figure(ledger).axes[0].get_xticklabels()]
    assert [label.rsplit(", ", 1)[1] for label in labels] == ["3 folds", "leave one out"], labels

    older = [{k: v for k, v in line.items() if k != "plan"} for line in LEDGER]
    labels = [t.get_text() for t in ledger_figure(older).axes[0].get_xticklabels()]
    assert [label.rsplit(", ", 1)[1] for label in labels] == ["cross-validated", "test split"], labels



def test_the_history_shows_what_a_fit_that_fell_back_asked_for(tmp_path: Path) -> None:
    """Fits that fell back to the rigid fit were four identical rows ("rigid, 5.75 mm"): the
    ledger keeps what was asked and how it scored held out (the figure fit's note gives, the
    rigid fit's held-out block as the truth it lost to), and the history says it."""
    from posecorr.analysis.ledger import read_ledger

    data = tmp_path / "exp1.csv"
    data.write_bytes((Path(__file__).parent / "data" / "realdata" / "20201002_Exp1.csv").read_bytes())
    out = _cli("fit", "exp1.csv", "-o", "m.onnx", "--method", "pmc", "--cv", "4", cwd=tmp_path)
    entry = read_ledger(data)[-1]
    assert entry["fell_back"] and entry["method"] == "rigid" and out["fell_back_to_rigid"]
    asked = entry["asked"]
    assert asked["name"] == "pmc-zhou" and asked["on"] == "held-out"
    assert asked["rmse_total"] > entry["cv"]["rmse_total"] == entry["baseline"]["rmse_total"]
    assert any(f"{asked['rmse_total']:.4g}" in note for note in out["notes"]), (asked, out["notes"])
    _cli("report", "exp1.csv", "--model", "m.onnx", "-o", "r.html", "--no-diagnosis", cwd=tmp_path)
    method = html.unescape(_history_rows((tmp_path / "r.html").read_text())[0][4])
    assert method.startswith("rigid (asked: pmc-zhou, ") and "held-out rmse_total; worse than the rigid fit" in method



def test_the_ledger_names_the_model_as_seen_from_the_data(tmp_path: Path) -> None:
    """A fit run from another directory recorded the model by that directory's path: the
    ledger, beside the data, now names it from there, whatever the working directory."""
    from posecorr.analysis.ledger import read_ledger
    from posecorr.data import write_table
    from posecorr.simulate import simulate_session

    (tmp_path / "cell" / "models").mkdir(parents=True)
    write_table(simulate_session(1, n=12, spread="full", position_only=False).table, tmp_path / "cell" / "s.csv")
    _cli("fit", "cell/s.csv", "-o", "cell/models/m.onnx", "--effects", "station,mount", "--method", "none",
         "--cv", "3", cwd=tmp_path)
    _cli("fit", "s.csv", "-o", str(tmp_path / "m2.onnx"), "--effects", "station,mount", "--method", "none",
         "--cv", "3", cwd=tmp_path / "cell")
    assert [line["model"] for line in read_ledger(tmp_path / "cell" / "s.csv")] == [
        str(Path("models") / "m.onnx"), str(Path("..") / "m2.onnx")]


# --- the page in a real browser ------------------------------------------------------------

def _chromium() -> None:
    """Skip without a Chromium, unless on CI (CI=true), where `.ci/run` installs Debian's."""
    import os

    from posecorr.analysis.screenshot import BROWSERS, find_browser

    if find_browser() is None:
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(f"CI=true and no Chromium on PATH ({', '.join(BROWSERS)}): "
                        "install Debian's chromium (.ci/run's apt-get line)")
        pytest.skip("no Chromium on PATH (install Debian's chromium to run the browser test)")


def test_the_page_in_headless_chromium(tmp_path: Path, unregistered: PoseTable) -> None:
    """Every figure decodes (naturalWidth > 0), every anchor of the menu resolves to a section,
    neither a script error nor a console message shows and no text runs past its section's
    edges, in a real Chromium."""
    from posecorr.analysis.screenshot import check_page

    _chromium()
    corrected = unregistered.reference.copy()
    corrected[:, :3] += np.random.default_rng(2).normal(0, 0.3e-3, (unregistered.n, 3))
    info = {"file": "m.onnx", "method": "pmc", "representation": "zhou", "effects": ["station", "mount"]}
    out = write_report(tmp_path / "r.html", unregistered, corrected, info, DIAGNOSIS, LEDGER)
    _, parsed = _parse(out)
    seen = check_page(out, tmp_path, timeout=120)
    assert len(seen["images"]) == len(parsed.imgs) == 7
    undecoded = [i["alt"] for i in seen["images"] if not (i["complete"] and i["width"] > 0 and i["height"] > 0)]
    assert not undecoded, f"figures that do not decode in Chromium: {undecoded}"
    assert [a["href"] for a in seen["anchors"]] == [f"#{sid}" for sid, _ in SECTIONS if sid != "segments"]
    assert all(a["resolves"] for a in seen["anchors"]), [a for a in seen["anchors"] if not a["resolves"]]
    assert seen["errors"] == [] and seen["console"] == []
    assert {sid: s["outside"] for sid, s in seen["sections"].items() if s["outside"]} == {}


def test_the_browser_check_sees_a_broken_page(tmp_path: Path) -> None:
    """The check can fail: a figure that does not decode, a menu anchor to nothing, a script
    error, a console message and text past a section's edges are each seen."""
    from posecorr.analysis.screenshot import check_page

    _chromium()
    page = tmp_path / "bad.html"
    page.write_text('<!DOCTYPE html><html><head><meta charset="utf-8"></head><body><nav><a href="#gone">x</a>'
                    '<a href="#s">s</a></nav><section id="s"><img alt="broken" src="data:image/png;base64,AAAA">'
                    '<script>console.log("a message"); missing();</script><p style="margin-left:-60px">'
                    'out on the left</p><pre>' + "past the right edge " * 40 + '</pre></section></body></html>')
    seen = check_page(page, tmp_path, timeout=120)
    assert seen["sections"]["s"]["outside"] == ["out on the left", ("past the right edge " * 40).strip()[:80]]
    assert seen["images"][0]["width"] == 0
    assert [a["resolves"] for a in seen["anchors"]] == [False, True]
    assert any("missing is not defined" in e for e in seen["errors"])
    assert any("failed to load <img>" in e for e in seen["errors"])
    assert any("a message" in c for c in seen["console"])


def _many_held(table: PoseTable) -> dict:
    """A model's metadata as the real 9-pose session's quadratic fit wrote it: mount.e held
    whole, 11 of quadratic.q's 18 dimensions held along directions, each of 18 numbers."""
    rng = np.random.default_rng(3)
    opening = "positions spread (243, 163, 87) mm RMS along their principal axes"
    fixed = {"mount.e": "orientations within 0.4 deg of their mean: only 0% of its effect on these poses is its own"}
    for k in range(11):
        direction = "[" + ", ".join(f"{v:.2f}" for v in rng.uniform(-0.6, 0.6, 18)) + "]"
        fixed[f"quadratic.q along {direction}"] = f"{opening}: its standard error would be {100 + k} x its typical size"
    return {"file": "e2q_" + "x" * 120 + ".onnx", "method": "none", "effects": ["station", "mount", "quadratic"],
            "fixed": fixed}


def test_a_parameter_held_along_many_directions_is_one_row(tmp_path: Path, small) -> None:
    """11 held directions of quadratic.q were 11 rows "held (not determined): quadratic.q along
    [18 numbers]": now one row per parameter, the directions in a collapsed list, the shared
    reason said once in its summary line."""
    table, corrected = small
    info = _many_held(table)
    text, _ = _parse(write_report(tmp_path / "r.html", table, corrected, info, None, []))
    summary = text[text.index('id="summary"'):text.index('id="metrics"')]
    labels = re.findall(r"<dt>held \(not determined\): ([^<]*)</dt>", summary)
    assert labels == ["mount.e", "quadratic.q"]
    held = summary[summary.index("<dt>held (not determined): quadratic.q</dt>"):]
    held = held[:held.index("</details>")]
    assert ("<summary>11 directions held: positions spread (243, 163, 87) mm RMS along their principal axes"
            "</summary>") in held
    items = re.findall(r"<li>along (\[[^]]*\]): its standard error would be (\d+) x its typical size</li>", held)
    assert [f"quadratic.q along {d}" for d, _ in items] == [k for k in info["fixed"] if k != "mount.e"]
    assert [int(v) for _, v in items] == list(range(100, 111))
    assert "<dd>orientations within 0.4 deg of their mean: only 0% of its effect on these poses is its own</dd>" in summary


def test_the_summary_of_many_held_directions_stays_inside_its_card(tmp_path: Path, small) -> None:
    """In Chromium the 11 labels "held (not determined): quadratic.q along [18 numbers]" took the
    label column's max-content width: the values were squeezed to ~80 px, their text ran past
    the card's edge and the summary was ~1,300 px tall. Now the labels wrap in a bounded
    column, the values keep most of the card, no text leaves it (a long model file name
    neither) and the summary is a few lines."""
    from posecorr.analysis.screenshot import check_page

    _chromium()
    table, corrected = small
    out = write_report(tmp_path / "r.html", table, corrected, _many_held(table), None, [])
    summary = check_page(out, tmp_path, timeout=120, width=1400)["sections"]["summary"]
    assert summary["outside"] == []
    label, value = summary["kv_columns"]
    assert label < 0.3 * summary["width"] and value > 0.6 * summary["width"], summary
    assert summary["height"] < 500, summary


@pytest.mark.parametrize("key", ["name", "model"])
def test_a_ledger_line_that_cannot_rebuild_the_held_out_says_why(unregistered: PoseTable, key: str) -> None:
    """In-sample, with the reason, for a line of an older posecorr, of another table, or one
    whose plan cannot be read; the rigid variant the line names is kept, under the key fit
    writes ("name") or the one older ledgers hold ("model")."""
    from posecorr.analysis.comparison import compare

    table = unregistered
    baseline = {key: "rigid-kabsch", "rmse_pos": 0.02}
    cases = [({"cv": {}, "baseline": baseline}, "lacks plan, seed, n"),
             ({"plan": "5", "seed": 0, "n": table.n + 1, "baseline": baseline}, f"{table.n + 1} poses"),
             ({"plan": "5 folds of", "seed": 0, "n": table.n, "baseline": baseline, "effects": ["station"],
               "spec": {"method": "auto", "representation": "zhou"}}, "could not be rebuilt from the ledger line")]
    for entry, why in cases:
        comparison = compare(table, table.reference, entry)
        assert not comparison.held_out and comparison.scored == "in-sample"
        assert why in comparison.reason
        assert comparison.baseline == "rigid fit (kabsch)"
        assert comparison.to_json()["baseline"]["name"] == comparison.rigid_name == "rigid-kabsch"


# --- a session of a few poses: no noise drawn as a trend -------------------------------------

def test_a_median_point_stands_for_three_poses_or_more() -> None:
    from posecorr.analysis.figures import MIN_PER_GROUP, _binned_median

    rng = np.random.default_rng(4)
    x, y = rng.permutation(np.arange(11.0)), rng.uniform(1, 10, 11)
    mx, my = _binned_median(x, y)
    by_x = y[np.argsort(x)]
    # 11 distinct poses: three equal-count bins (4, 4, 3), each point the median of its bin.
    assert np.allclose(my, [np.median(by_x[:4]), np.median(by_x[4:8]), np.median(by_x[8:])])
    assert np.allclose(mx, [1.5, 5.5, 9.0])
    assert _binned_median(x[:5], y[:5])[0].size == 0  # fewer than two bins of three: no line
    # A few distinct values, each held by three poses or more (a lattice): one point per value.
    lattice = np.repeat([0.0, 1.0, 2.0], MIN_PER_GROUP + 1)
    values = rng.uniform(1, 10, lattice.size)
    mx, my = _binned_median(lattice, values)
    assert np.allclose(mx, [0, 1, 2]) and np.allclose(my, [np.median(values[lattice == v]) for v in (0, 1, 2)])


def test_a_few_poses_are_boxed_three_or_more_and_counted_in_whole_poses() -> None:
    from posecorr.analysis.figures import MIN_PER_GROUP, _groups, features_figure, histogram_figure, orientation_figure

    yaw = np.linspace(75.0, 99.0, 11)  # 11 distinct yaws: one pose per value
    labels, index = _groups(yaw)
    assert min(map(len, index)) >= MIN_PER_GROUP and len(labels) == len(index) == 3
    assert labels == ["≈79", "≈88", "≈97"]   # each bin's median, whole degrees: ranges overlapped
    assert sorted(np.concatenate(index).tolist()) == list(range(11))
    many = np.repeat([10.0, 20.0, 30.0], 5)  # few values, each of five poses: grouped by value
    assert _groups(many)[0] == ["10", "20", "30"]

    rng = np.random.default_rng(5)
    five = {"x": rng.uniform(0, 1, 5), "yaw": np.radians(rng.uniform(0, 90, 5))}
    fig = features_figure(five, rng.uniform(1, 9, 5), rng.uniform(1, 9, 5), "position error", "mm")
    assert all(not ax.get_lines() for ax in fig.axes[:2])
    legend = [t.get_text() for ax in fig.axes for lg in [ax.get_legend()] if lg for t in lg.get_texts()]
    assert legend and not any("median" in t for t in legend)

    fig = histogram_figure((rng.uniform(1, 9, 11), rng.uniform(1, 9, 11)), None)
    ticks = fig.axes[0].get_yticks()
    assert np.allclose(ticks, np.round(ticks))
    # errors within one decade (a rotation error 0.3-1.3 mrad): labels at 1, 2 and 5 x 10^k, not
    # the one decade label that leaves "1" alone; before's RMSE dashed, after's solid
    fig = histogram_figure((rng.uniform(0.3, 1.3, 50), rng.uniform(0.3, 1.3, 50)), None)
    fig.canvas.draw()
    ax = fig.axes[0]
    lo, hi = ax.get_xlim()
    shown = [t.get_text() for t, v in zip(ax.get_xticklabels(), ax.get_xticks()) if lo <= v <= hi]
    assert len(shown) >= 3 and "0.5" in shown and "1" in shown, shown
    assert [line.get_linestyle() for line in ax.get_lines()] == ["--", "-"]

    # a box's count once where every box holds the same (nine poses of one orientation: "9", not "9–9")
    still = {"roll": np.zeros(9), "pitch": np.zeros(9), "yaw": np.full(9, 1.5)}
    fig = orientation_figure(still, rng.uniform(1, 9, 9), None, rng.uniform(1, 9, 9), None)
    assert fig.axes[0].get_title() == "position error by roll (n per box: 9)"
    eleven = {"roll": np.zeros(11), "pitch": np.zeros(11), "yaw": np.radians(yaw)}
    fig = orientation_figure(eleven, rng.uniform(1, 9, 11), None, rng.uniform(1, 9, 11), None)
    assert fig.axes[2].get_title() == "position error by yaw (n per box: 3–4)"


def test_no_structure_reads_as_one_line_and_a_form_is_named_as_one(tmp_path: Path,
                                                                   small: tuple[PoseTable, np.ndarray]) -> None:
    table, corrected = small
    flat = {**DIAGNOSIS, "features": [{"feature": "x", "r2": 0.0}, {"feature": "yaw", "r2": 0.0}]}
    text, parsed = _parse(write_report(tmp_path / "flat.html", table, corrected, None, flat))
    section = text[text.index('id="diagnosis"'):text.index('id="ledger"')]
    assert "None: a smooth fit along a feature explains none of the held-out residual" in section
    assert "R² 0 along x, yaw" in section and "cv R²</th>" not in section
    assert len(parsed.imgs) == 5  # workspace, features (pos, rot), orientation, histograms: no R² bars

    mixed = {**DIAGNOSIS, "features": [{"feature": "x", "r2": 0.0}, {"feature": "yaw", "r2": 0.4}]}
    section = _parse(write_report(tmp_path / "mixed.html", table, corrected, None, mixed))[0]
    section = section[section.index('id="diagnosis"'):section.index('id="ledger"')]
    assert section.count('<td class="l">yaw</td>') == 1 and '<td class="l">x</td>' not in section
    assert "R² 0 along x." in section

    form = {"candidates": [{"effect": "strain", "kind": "form", "rank": 1, "p_value": 1e-9, "present": True,
                            "cv_rmse_before": 7e-3, "cv_rmse_after": 1.5e-3}]}
    line = takeaway(form, ["station", "mount"])
    assert line.startswith("Most likely missing: strain, a form outside the catalogue (present: yes")
    assert line.endswith("--effects station,mount,strain")
    assert takeaway({"candidates": [], "features": []}).endswith("nothing tried explains what is left.")


def test_in_the_model_code_and_a_best_row_read_as_they_are(tmp_path: Path, small: tuple[PoseTable, np.ndarray]) -> None:
    """A form held because the model has it already sits under its own heading, naming that
    effect; Markdown `code` in the words shows as <code>, never as backticks; the corrected row
    is highlighted only where it is better than the before."""
    table, corrected = small
    diag = {**DIAGNOSIS, "undetermined": [
        {"effect": "strain", "in_model": "session_strain", "same": True,
         "reason": "strain.s: only 0% of its effect on these poses is its own (the rest is what session_strain does)"},
        {"effect": "orientation_bias",
         "reason": "orientation_bias.k: only 0% of its effect on these poses is its own"}]}
    text, _ = _parse(write_report(tmp_path / "r.html", table, corrected, None, diag))
    section = text[text.index('id="diagnosis"'):text.index('id="ledger"')]
    held = section[section.index("<h3>Not ranked: already in the model</h3>"):]
    held = held[:held.index("</ul>")]
    assert "<b>strain</b> is already in the model as session_strain: strain.s" in held
    assert "orientation_bias" not in held
    unseen = section[section.index("<h3>Not ranked: this data cannot determine them</h3>"):]
    assert "<b>orientation_bias</b> cannot be determined by this data" in unseen[:unseen.index("</ul>")]
    assert "`" not in text
    metrics = text[text.index('id="metrics"'):text.index('id="workspace"')]
    assert metrics.count('class="best"') == 1

    text, _ = _parse(write_report(tmp_path / "same.html", table, table.measured.copy(), None, None))
    assert "<code>posecorr diagnose</code>" in text and "`" not in text
    metrics = text[text.index('id="metrics"'):text.index('id="workspace"')]
    assert 'class="best"' not in metrics   # equal rows: nothing is better


def test_the_arrow_key_stays_inside_its_panel_off_the_title() -> None:
    """On the real 11-pose session the workspace panels' scale key ("10 mm") sat on the title
    line and its arrow ran out of the panel: the key, text and arrow, is inside its panel."""
    from matplotlib.quiver import QuiverKey

    from posecorr.analysis.figures import workspace_figure
    from posecorr.data import read_table

    ref_p = read_table(Path(__file__).parent / "data" / "realdata" / "20201002_Exp1.csv").ref_p
    rng = np.random.default_rng(0)
    fig = workspace_figure(ref_p, rng.normal(0, 5e-3, ref_p.shape), rng.normal(0, 5e-4, ref_p.shape),
                           "before: rigid fit (joint)", "after: held-out")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    keys = [(ax, k) for ax in fig.axes for k in ax.get_children() if isinstance(k, QuiverKey)]
    assert len(keys) == 6
    for ax, key in keys:
        text = key.text.get_window_extent(renderer)
        assert text.y1 <= ax.bbox.y1 and text.x0 >= ax.bbox.x0, ax.get_title()
        assert not text.overlaps(ax.title.get_window_extent(renderer)), ax.get_title()
        arrow = key.vector
        start = arrow.get_offset_transform().transform(arrow.get_offsets())[0]
        ends = np.concatenate([arrow.get_transform().transform(p.vertices) + start for p in arrow.get_paths()])
        assert ends[:, 0].max() <= ax.bbox.x1 and ends[:, 1].max() <= ax.bbox.y1, ax.get_title()


def _arrow_rows(fig) -> list[dict]:
    """Per row of the workspace figure: its quivers' scales and colour limits, its keys'
    lengths (m) and its panels' titles."""
    from matplotlib.quiver import Quiver, QuiverKey

    rows = []
    for panels in (fig.axes[:3], fig.axes[3:6]):
        quivers = [c for ax in panels for c in ax.collections if isinstance(c, Quiver)]
        rows.append({"scale": {q.scale for q in quivers}, "clim": {q.get_clim() for q in quivers},
                     "key": {k.U for ax in panels for k in ax.get_children() if isinstance(k, QuiverKey)},
                     "titles": [ax.get_title() for ax in panels]})
    return rows


def test_the_arrow_rows_share_a_magnification_unless_the_after_arrows_would_vanish() -> None:
    """The rows had a magnification and a colour scale each, said only in the figure's title:
    on the real 9-pose session (after 0.6 of before) both keys read 20 mm, the after's arrows
    were drawn 1.7x longer, a 16 mm error as long as a 30 mm one. Now the rows share one
    magnification, colour scale and colour bar; where the after's arrows would be dots at the
    before's (the loop session, 1/8), the after row is magnified more and every title says
    by how much."""
    from posecorr.analysis.figures import workspace_figure
    from posecorr.data import read_table

    ref_p = read_table(Path(__file__).parent / "data" / "realdata" / "20201002_Exp1.csv").ref_p
    before = np.random.default_rng(0).normal(0, 5e-3, ref_p.shape)
    fig = workspace_figure(ref_p, before, 0.6 * before[::-1], "before: rigid fit (joint)", "after: held-out")
    top, bottom = _arrow_rows(fig)
    assert len(top["scale"]) == 1 and top["scale"] == bottom["scale"]
    assert len(top["clim"]) == 1 and top["clim"] == bottom["clim"]
    assert len(top["key"]) == 1 and top["key"] == bottom["key"]
    assert len(fig.axes) == 7                                            # one colour bar
    assert not any("magnified" in t for t in top["titles"] + bottom["titles"])

    fig = workspace_figure(ref_p, before, before[::-1] / 8, "before: rigid fit (joint)", "after: held-out")
    top, bottom = _arrow_rows(fig)
    (above,), (below,) = top["scale"], bottom["scale"]
    assert above / below == pytest.approx(8)
    assert top["clim"] != bottom["clim"] and len(fig.axes) == 8           # a colour bar each
    assert all(t.endswith("\nmagnified 8× less than the after row") for t in top["titles"]), top["titles"]
    assert all(t.endswith("\nmagnified 8× more than the before row") for t in bottom["titles"]), bottom["titles"]
    assert top["key"] == {0.01} and bottom["key"] == {0.001}


def test_the_page_says_whether_the_arrow_rows_share_a_magnification(tmp_path: Path, small) -> None:
    """The page's keys (data-*-key-mm, report --json's "arrows") are those drawn, and its note
    says whether the rows share a magnification and, where not, how they compare."""
    from posecorr.analysis.comparison import compare

    table, corrected = small
    closer = table.measured.copy()
    closer[:, :3] = table.ref_p + 0.6 * (table.meas_p - table.ref_p)   # the after 0.6 of the before
    for after, shared in ((closer, True), (corrected, False)):
        keys = compare(table, after).to_json()["arrows"]
        text, _ = _parse(write_report(tmp_path / "r.html", table, after, None, None, []))
        section = text[text.index('id="workspace"'):text.index('id="features"')]
        assert (f'data-before-key-mm="{keys["before_key_mm"]:g}" data-after-key-mm="{keys["after_key_mm"]:g}"'
                in section)
        assert (keys["before_key_mm"] == keys["after_key_mm"]) is shared
        assert ("Both rows have one magnification and one colour scale." in section) is shared
        assert ("the after row is magnified" in section and "× more than the before row (compare the keys: "
                f'{keys["before_key_mm"]:g} mm above, {keys["after_key_mm"]:g} mm below)' in section) is not shared


def test_the_feature_panels_tick_labels_do_not_run_into_each_other() -> None:
    """On the real 11-pose session the z panel (the poses within 30 mm of one height) read
    '-0.030-0.025-0.020-0.015-0.010-0.0050.000': every panel's x labels stand apart."""
    from posecorr.analysis.features import table_features
    from posecorr.analysis.figures import features_figure
    from posecorr.data import read_table

    table = read_table(Path(__file__).parent / "data" / "realdata" / "20201002_Exp1.csv")
    features = table_features(table)
    rng = np.random.default_rng(0)
    fig = features_figure(features, rng.uniform(1, 9, table.n), rng.uniform(1, 9, table.n), "position error", "mm")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    panels = [ax for ax in fig.axes if ax.get_xlabel()]
    assert any(ax.get_xlabel() == "z [m]" for ax in panels)
    for ax in panels:
        boxes = [t.get_window_extent(renderer) for t in ax.get_xticklabels() if t.get_visible() and t.get_text()
                 and ax.get_xlim()[0] <= t.get_position()[0] <= ax.get_xlim()[1]]
        assert len(boxes) >= 2, ax.get_xlabel()
        for left, right in zip(boxes, boxes[1:]):
            assert left.x1 < right.x0, (ax.get_xlabel(), [t.get_text() for t in ax.get_xticklabels()])


def test_a_long_diagnosis_is_announced_with_the_way_around_it(tmp_path: Path, capsys, monkeypatch) -> None:
    """From LONG_DIAGNOSIS_POSES poses on, the report says before its diagnosis that it takes
    minutes and how to leave it out; below, it does not (the threshold moved to a 12-pose
    session's size, so that the diagnosis stays seconds)."""
    from posecorr.cli import main
    from posecorr.cli import report as report_cli
    from posecorr.data import write_table

    table = simulate(3, seed=2).table.subset(np.arange(12))
    path, model = tmp_path / "s.csv", tmp_path / "m.onnx"
    write_table(table, path)
    assert main(["fit", str(path), "--method", "none", "--cv", "3", "-o", str(model)]) == 0
    said = []
    for threshold in (12, 13):
        monkeypatch.setattr(report_cli, "LONG_DIAGNOSIS_POSES", threshold)
        capsys.readouterr()
        assert main(["report", str(path), "--model", str(model), "--cv", "3", "--workers", "1",
                     "-o", str(tmp_path / "r.html")]) == 0
        said.append(capsys.readouterr().err)
    announced = ("the diagnosis of 12 poses refits each candidate on every fold, in 1 process (--workers): minutes "
                 "on a table this size (--no-diagnosis leaves it out)")
    assert announced in said[0] and "the diagnosis of" not in said[1]
