"""Pose tables: round trip, position-only tables, and every malformed case."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr.data import PoseTable, TableError, TableReader, read_table, require_rows, write_table


def _table(n: int = 5, with_orientation: bool = True) -> PoseTable:
    rng = np.random.default_rng(0)
    q = Rotation.random(n, random_state=1).as_quat(scalar_first=True)
    return PoseTable(rng.normal(size=(n, 3)), q, rng.normal(size=(n, 3)),
                     Rotation.random(n, random_state=2).as_quat(scalar_first=True) if with_orientation else None,
                     {"t": np.arange(n, dtype=float) * 10, "session": np.array(["a"] * n, dtype=object)})


def _write(tmp_path, text: str):
    path = tmp_path / "poses.csv"
    path.write_text(text)
    return path


HEADER = "meas_x,meas_y,meas_z,meas_qw,meas_qx,meas_qy,meas_qz,ref_x,ref_y,ref_z"
ROW = "0.1,0.2,0.3,1,0,0,0,0.1,0.2,0.3"


@pytest.mark.parametrize("with_orientation", [True, False])
def test_round_trip_is_exact(tmp_path, with_orientation: bool) -> None:
    table = _table(with_orientation=with_orientation)
    write_table(table, tmp_path / "t.csv")
    back = read_table(tmp_path / "t.csv")
    np.testing.assert_array_equal(back.meas_p, table.meas_p)
    np.testing.assert_array_equal(back.meas_q, table.meas_q)
    np.testing.assert_array_equal(back.ref_p, table.ref_p)
    assert back.has_orientation == with_orientation
    if with_orientation:
        np.testing.assert_array_equal(back.ref_q, table.ref_q)
    np.testing.assert_array_equal(back.extras["t"], table.extras["t"])
    assert list(back.extras["session"]) == ["a"] * 5


def test_position_only_reference_keeps_measured_orientation(tmp_path) -> None:
    table = read_table(_write(tmp_path, f"{HEADER}\n{ROW}\n"))
    assert not table.has_orientation
    np.testing.assert_array_equal(table.reference[:, 3:], table.measured[:, 3:])


def test_unknown_columns_are_kept(tmp_path) -> None:
    table = read_table(_write(tmp_path, f"{HEADER},operator\n{ROW},alice\n"))
    assert list(table.extras["operator"]) == ["alice"]
    write_table(table, tmp_path / "out.csv")
    assert "operator" in (tmp_path / "out.csv").read_text().splitlines()[0]


def test_a_misspelled_optional_column_is_kept_with_one_warning_naming_the_likely_one(tmp_path, capsys) -> None:
    """`jiter_mm` for `jitter_mm` is kept as an unknown column, as any unknown one, but its
    meaning would be lost unsaid: one warning line names the file, the column and jitter_mm;
    a column far from every known name (operator) draws none."""
    path = _write(tmp_path, f"{HEADER},jiter_mm,operator\n{ROW},0.2,alice\n")
    table = read_table(path)
    assert list(table.extras["jiter_mm"]) == ["0.2"] and "jitter_mm" not in table.extras
    assert capsys.readouterr().err == (f"posecorr: warning: {path}: column 'jiter_mm' is not one posecorr knows "
                                       "and is kept as is; did you mean jitter_mm?\n")
    read_table(_write(tmp_path, f"{HEADER},jitter_mm,jiter_mm\n{ROW},0.2,0.3\n"))
    assert capsys.readouterr().err == ""  # beside the known column it is no misspelling of it


def test_reference_angles_are_named_not_taken_for_a_quaternion(tmp_path, capsys) -> None:
    """ref_rx, ref_ry, ref_rz (a robot's rotation vector) drew 'did you mean ref_qx?' three
    times, and the table was read position-only without a word on why."""
    path = _write(tmp_path, HEADER + ",ref_rx,ref_ry,ref_rz\n" + ROW + ",0.1,0.2,0.3\n")
    assert not read_table(path).has_orientation
    assert capsys.readouterr().err.splitlines() == [
        f"posecorr: warning: {path}: columns 'ref_rx', 'ref_ry', 'ref_rz' look like angles (Euler or a rotation "
        "vector), and posecorr reads the reference orientation as unit quaternions ref_qw..ref_qz: without them the "
        "table is read position-only; convert them (scipy: Rotation.from_euler(sequence, angles, degrees=True), or "
        "from_rotvec, then .as_quat(scalar_first=True))"]


@pytest.mark.parametrize("text, row, column, what", [
    (HEADER.replace(",ref_z", "") + "\n" + ROW.rsplit(",", 1)[0] + "\n", 1, "ref_z", "missing column"),
    (f"{HEADER},ref_qw\n{ROW},1\n", 1, "ref_qx", "missing column"),
    (f"{HEADER}\n{ROW}\n0.1,abc,0.3,1,0,0,0,0.1,0.2,0.3\n", 3, "meas_y", "expected a number, got 'abc'"),
    # two logs joined with cat: the second's header inside the table, named as such
    (f"{HEADER}\n{ROW}\n{HEADER}\n{ROW}\n", 3, "meas_x", "expected a number, got 'meas_x', its column's name: a "
     "header row again (tables joined? keep the first header only)"),
    (f"{HEADER}\n{ROW}\n0.1,0.2,nan,1,0,0,0,0.1,0.2,0.3\n", 3, "meas_z", "finite"),
    (f"{HEADER}\n{ROW}\n0.1,0.2,0.3,1,0,0,0,inf,0.2,0.3\n", 3, "ref_x", "finite"),
    (f"{HEADER}\n{ROW}\n0.1,0.2,0.3,1,0,0,0,,0.2,0.3\n", 3, "ref_x", "empty value"),
    (f"{HEADER}\n{ROW}\n\n0.1,0.2,0.3,1.01,0,0,0,0.1,0.2,0.3\n", 4, "meas_qw..meas_qz", "quaternion norm"),
    (f"{HEADER}\n{ROW}\n0.1,0.2\n", 3, None, "2 fields, expected 10"),
    (f"{HEADER}\n{ROW}\n".replace(",", ";"), 1, "meas_x", "the header is one column holding ';': posecorr reads commas"),
    (f"# session 3\n\n{HEADER},ref_qw\n{ROW},1\n", 3, "ref_qx", "missing column"),   # the header's own row
    # a required column mistyped: the column in its place is named
    (HEADER.replace("ref_y", "refy") + f"\n{ROW}\n", 1, "ref_y", "the header has 'refy': is it ref_y?"),
    (HEADER.replace("meas_x", "meas_X") + f"\n{ROW}\n", 1, "meas_x", "the header has 'meas_X': is it meas_x?"),
    (HEADER.replace("ref_x", "ref_x_m") + f"\n{ROW}\n", 1, "ref_x", "the header has 'ref_x_m': is it ref_x?"),
    (f"{HEADER},ref_qw,ref_qx,ref_qy,ref_gz\n{ROW},1,0,0,0\n", 1, "ref_qz", "the header has 'ref_gz': is it ref_qz?"),
    (f"# v2\n{HEADER}\n{ROW}\n#{ROW}\n0.1,0.2\n", 5, None, "2 fields, expected 10"),  # comment lines count
    # what stands in for a missing column, from an audit that brought its own tables
    (HEADER.replace("meas_x", "meas_x [m]") + f"\n{ROW}\n", 1, "meas_x",
     "the header has 'meas_x [m]': name the column meas_x, without a unit (posecorr reads positions in metres)"),
    (HEADER.replace("meas_qw,meas_qx,meas_qy,meas_qz", "meas_roll,meas_pitch,meas_yaw") + "\n", 1, "meas_qw",
     "the header has 'meas_roll', 'meas_pitch', 'meas_yaw': posecorr reads orientations as unit quaternions "
     "meas_qw..meas_qz, not angles"),
    ("stamp,tx,ty,tz,qw,qx,qy,qz,rx,ry,rz\n", 1, "meas_x",
     "the header has 'stamp', 'tx', 'ty', 'tz', 'qw', 'qx', 'qy', 'qz', 'rx', 'ry', 'rz'"),
    (f"{HEADER}\n{ROW}\n0.1,0.2,0.3,0.99,0.01,0.01,0.01,0.1,0.2,0.3\n", 3, "meas_qw..meas_qz",
     "(expected a unit quaternion w, x, y, z); normalise the quaternions if they were rounded (4 decimals keep "
     "the norm within 0.001)"),
    (f"{HEADER}\n{ROW}\n0,0,0,0,0,0,0,0.1,0.2,0.3\n", 3, "meas_qw..meas_qz",
     "a zero quaternion (expected a unit quaternion w, x, y, z); a tracker that lost tracking writes zeros: "
     "remove the row"),
])
def test_malformed_tables_name_file_row_and_column(tmp_path, text, row, column, what) -> None:
    path = _write(tmp_path, text)
    with pytest.raises(TableError) as info:
        read_table(path)
    message = str(info.value)
    assert message.startswith(str(path))
    assert f"row {row}" in message
    if column:
        assert f"column {column}" in message
    assert what in message
    assert "\n" not in message


def test_quaternion_sign_is_free_and_small_norm_error_accepted(tmp_path) -> None:
    table = read_table(_write(tmp_path, f"{HEADER}\n0,0,0,-0.9995,0,0,0,0,0,0\n"))
    assert table.meas_q[0, 0] == -0.9995


def test_missing_file_and_empty_file(tmp_path) -> None:
    with pytest.raises(TableError, match="cannot open"):
        read_table(tmp_path / "nope.csv")
    with pytest.raises(TableError, match="empty file"):
        read_table(_write(tmp_path, ""))


def test_too_few_rows_for_a_fit(tmp_path) -> None:
    table = read_table(_write(tmp_path, f"{HEADER}\n{ROW}\n{ROW}\n"))
    with pytest.raises(TableError, match=r"2 rows, but a quadratic fit needs at least 10"):
        require_rows(table, 10, "a quadratic fit")


def test_each_pose_keeps_its_file_row_through_subset_draw_and_correction(tmp_path) -> None:
    """Blank lines (empty, spaces, only commas) and the header make a pose's file row differ
    from its index + 2: the table keeps the row every message names, in chunks as whole, and
    a table made in memory has none."""
    rows = [ROW.replace("0.1,", f"0.{i},", 1) for i in range(1, 7)]
    text = "\n".join([HEADER, rows[0], "", rows[1], "   ", ",,,,,,,,,", rows[2], rows[3], "", rows[4], rows[5]])
    path = _write(tmp_path, text + "\n")
    expected = [2, 4, 7, 8, 10, 11]
    table = read_table(path)
    np.testing.assert_array_equal(table.rows, expected)
    np.testing.assert_array_equal(table.meas_p[:, 0], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6])
    with TableReader(path) as reader:   # apply's chunks name the same rows
        assert [c.row_numbers for c in reader.chunks(4)] == [expected[:4], expected[4:]]
    np.testing.assert_array_equal(table.subset(np.array([5, 1])).rows, [11, 4])
    drawn, keep = table.draw(3, seed=1)
    np.testing.assert_array_equal(drawn.rows, np.asarray(expected)[keep])
    np.testing.assert_array_equal(table.with_measured(table.measured).rows, expected)
    assert _table().rows is None and _table().subset(np.arange(2)).rows is None
    with pytest.raises(ValueError, match="rows has shape"):
        PoseTable(table.meas_p, table.meas_q, table.ref_p, rows=np.arange(2))


def test_comment_lines_are_no_poses_and_keep_the_rows_of_the_rest(tmp_path, capsys) -> None:
    """A logger's preamble and a pose left out by hand ('#' first, as numpy's loadtxt and
    pandas read it): the table is the one without those lines, every other pose keeps the
    number of its line in the file, and the lines among the poses are named in one warning."""
    table = _table(6)
    plain = tmp_path / "plain.csv"
    write_table(table, plain)
    lines = plain.read_text().splitlines()
    preamble = ["# Vive Pro, 2026-11-29", '# stations A, "B (a quote opens no cell)']
    commented = preamble + lines[:3] + ["#" + lines[3], "# a note"] + lines[4:]
    path = _write(tmp_path, "\n".join(commented + ["# end"]) + "\n")
    got = read_table(path)
    expected = table.subset(np.array([0, 1, 3, 4, 5]))
    np.testing.assert_array_equal(got.measured, expected.measured)
    np.testing.assert_array_equal(got.reference, expected.reference)
    np.testing.assert_array_equal(got.extras["t"], expected.extras["t"])
    # the rows an editor shows: count the file's lines, skip the comment ones
    numbered = [i for i, line in enumerate(path.read_text().splitlines(), 1) if not line.startswith("#")][1:]
    np.testing.assert_array_equal(got.rows, numbered)
    assert capsys.readouterr().err.strip() == (f"posecorr: warning: {path}: rows 6, 7, 11 start with '#': read as "
                                               "comments, not data")
    # a header of its own after the comments: its errors name its line
    bad = _write(tmp_path, "# x\n\n" + HEADER.replace("meas_y", "meas_y,meas_y") + "\n")
    with pytest.raises(TableError, match=r"row 3, column meas_y: duplicate column in header"):
        read_table(bad)


def test_a_run_of_comment_lines_is_read_a_chunk_at_a_time(tmp_path, capsys) -> None:
    """Thousands of comment lines between two poses (a logger's status lines) are handed on
    at most `size` at a time, in order, not held until the next pose; a table of comments
    alone after its header is still "no data rows"."""
    table = _table(2)
    plain = tmp_path / "plain.csv"
    write_table(table, plain)
    header, first, second = plain.read_text().splitlines()
    notes = [f"# status {i}" for i in range(23)]
    path = _write(tmp_path, "\n".join([header, first] + notes + [second] + notes[:9]) + "\n")
    with TableReader(path) as reader:
        chunks = list(reader.chunks(4))
        trailing = reader.trailing
    assert max(len(c.comments) for c in chunks) == 4 and max(len(c.rows) for c in chunks) <= 4
    assert [text for c in chunks for _, text in c.comments] + trailing == notes + notes[:9]
    assert sum(len(c.rows) for c in chunks) == 2 and len(trailing) <= 4
    got = read_table(path)
    np.testing.assert_array_equal(got.measured, table.measured)
    only_notes = _write(tmp_path, "\n".join([header] + notes) + "\n")
    with pytest.raises(TableError, match="no data rows after the header"):
        read_table(only_notes)
    capsys.readouterr()


def test_a_commented_header_is_named_and_an_id_starting_with_a_hash_round_trips(tmp_path) -> None:
    """numpy's savetxt writes its header as '# meas_x,...': the error says so, not that the
    first pose's cells are no header. A cell that starts with '#' at the start of a row is
    written quoted, so that it reads back as a pose, not as a comment."""
    with pytest.raises(TableError, match=r"row 1: the line naming the columns starts with '#'"):
        read_table(_write(tmp_path, f"# {HEADER}\n{ROW}\n"))
    with pytest.raises(TableError, match=r"only comment lines, expected a header row"):
        read_table(_write(tmp_path, "# nothing yet\n\n"))
    table = _table(4)
    table.extras["id"] = np.array(["#1", "plain", '#"2"', "a\n#b"], dtype=object)
    path = tmp_path / "ids.csv"
    write_table(table, path)
    back = read_table(path)
    assert list(back.extras["id"]) == ["#1", "plain", '#"2"', "a\n#b"]   # a line inside a cell is the cell's
    np.testing.assert_array_equal(back.measured, table.measured)


def test_positions_spanning_more_than_a_cell_draw_a_units_warning(tmp_path, capsys) -> None:
    """A registered table in millimetres within 1000 mm of the base passes every cell check
    (it is under MAX_POSITION 'metres'): its spread, hundreds of 'metres', is what gives it
    away. One pose 99 m away (a glitch) is no unit mistake and draws no warning."""
    table = _table(6)
    table.ref_p = table.ref_p * 0.3
    table.meas_p = table.ref_p + 1e-3
    path = tmp_path / "m.csv"
    write_table(table, path)
    read_table(path)
    assert capsys.readouterr().err == ""
    glitch = PoseTable(table.meas_p.copy(), table.meas_q, table.ref_p, table.ref_q, table.extras)
    glitch.meas_p[2, 0] = 99.0
    write_table(glitch, path)
    read_table(path)
    assert capsys.readouterr().err == ""
    table.ref_p, table.meas_p = table.ref_p * 1000, table.meas_p * 1000
    assert np.abs(table.ref_p).max() < 1000
    write_table(table, path)
    read_table(path)
    err = capsys.readouterr().err.splitlines()
    spread = np.max(np.median(np.abs(table.ref_p - np.median(table.ref_p, axis=0)), axis=0))
    assert len(err) == 2 and "the measured positions lie a typical" in err[0]
    assert err[1].endswith(f"the reference positions lie a typical {spread:.4g} m from their median; posecorr reads "
                           "metres, and a tracked cell spans a few: are ref_x..ref_z in millimetres?")


def test_a_verb_that_fits_refuses_two_frames_in_two_units(tmp_path) -> None:
    """The reference in millimetres, the measured in metres: read with a warning, then fit
    went on and wrote a model that scored 258 m held out. A registration keeps distances: the
    frames' spreads 1000 times apart are two units, refused naming the columns. One pose 99 m
    off (a glitch) moves neither spread."""
    table = _table(8)
    table.ref_p = table.ref_p * 0.3
    table.meas_p = table.ref_p + 1e-3
    table.meas_p[2, 0] = 99.0
    require_rows(table, 3, "a fit")
    table.meas_p[2, 0] = table.ref_p[2, 0] + 1e-3
    table.ref_p = table.ref_p * 1000
    def spread(p: np.ndarray) -> float:   # the median absolute deviation of the worst axis
        return np.max(np.median(np.abs(p - np.median(p, axis=0)), axis=0))

    def refused() -> str:
        with pytest.raises(TableError) as info:
            require_rows(table, 3, "a fit")
        return str(info.value)

    assert refused().endswith(
        f"the reference positions lie a typical {spread(table.ref_p):.4g} m from their median and the measured "
        f"{spread(table.meas_p):.3g} m: a registration keeps distances, so the two are in units 1000 times apart "
        "(are ref_x..ref_z in millimetres or centimetres? posecorr reads metres)")
    table.meas_p = table.meas_p * 1000   # both in millimetres: the reading's warning, then refused
    assert refused().endswith(
        f"the measured positions lie a typical {spread(table.meas_p):.4g} m from their median and the reference "
        f"{spread(table.ref_p):.4g} m, where a tracked cell spans a few metres (are meas_x..meas_z and ref_x..ref_z in "
        "millimetres? posecorr reads metres)")


def test_repeated_rows_are_named(tmp_path, capsys) -> None:
    """Rows that repeat an earlier row's poses are kept (nothing is dropped unsaid) and named
    by file row in one warning: held out, a repeat keeps its twin in training."""
    table = _table(6)
    twice = table.subset(np.array([0, 1, 2, 1, 3, 4, 5, 0]))
    path = tmp_path / "twice.csv"
    write_table(twice, path)
    read = read_table(path)
    assert read.n == 8 and capsys.readouterr().err == ""   # said by a verb that fits, once
    require_rows(read, 3, "a fit")
    require_rows(read, 3, "a fit")
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].endswith(
        "twice.csv: 2 rows (5, 9) repeat an earlier row's measured and reference pose: a repeat held out keeps its "
        "twin in training, so held-out errors come out optimistic"), err
    write_table(table, path)
    require_rows(read_table(path), 3, "a fit")
    assert capsys.readouterr().err == ""


def test_a_tracker_that_held_its_last_pose_is_named(tmp_path, capsys) -> None:
    """A tracker that lost tracking reports its last pose again, to the bit, while the robot
    moves on: three such rows of a real session scored 410 mm leave-one-out (the session 5.7
    mm), without a word. Named by file row, with the row each repeats; kept."""
    table = _table(7)
    frozen = table.measured.copy()
    frozen[4] = frozen[3]
    frozen[5] = frozen[3]
    path = tmp_path / "frozen.csv"
    write_table(table.with_measured(frozen), path, comment="two rows frozen")
    require_rows(read_table(path), 3, "a fit")
    err = capsys.readouterr().err.splitlines()
    assert err == [f"posecorr: warning: {path}: 2 rows report exactly an earlier row's measured pose where the "
                   "reference moved (rows 7 as 6, 8 as 6): a tracker that lost tracking holds its last pose; kept, "
                   "fix or remove the row(s)"], err


def test_a_time_column_that_is_not_seconds_since_the_start_is_named(tmp_path, capsys) -> None:
    """t is seconds since the session's start: negative times and a span of days (a
    35-minute session in milliseconds) are said in a warning each; the table is read as is."""
    table = _table(6)
    path = tmp_path / "t.csv"
    table.extras["t"] = np.arange(6) * 420.0 * 1000                # 35 minutes, in ms
    write_table(table, path)
    read = read_table(path)
    require_rows(read, 3, "a fit")
    np.testing.assert_array_equal(read.time(), table.extras["t"])
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].endswith("column t spans 2.1e+06 s (24.3 days), and a session lasts minutes to "
                                             "hours: milliseconds? posecorr reads seconds"), err
    table.extras["t"] = np.arange(6) * 420.0 - 5000.0
    write_table(table, path)
    require_rows(read_table(path), 3, "a fit")
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "column t starts at -5000 s; t is seconds since the session's start" in err[0], err
    table.extras["t"] = np.arange(6) * 420.0
    write_table(table, path)
    require_rows(read_table(path), 3, "a fit")
    assert capsys.readouterr().err == ""


def test_a_table_of_several_sessions_is_named(tmp_path, capsys) -> None:
    """The session column is read, not modelled: a table naming two sessions says that one
    tracker frame and one mount are fitted to all its rows."""
    table = _table(6)
    table.extras["session"] = np.array(["s1", "s1", "s1", "s2", "s2", "s2"], dtype=object)
    path = tmp_path / "two.csv"
    write_table(table, path)
    read = read_table(path)
    require_rows(read, 3, "a fit")
    np.testing.assert_array_equal(read.extras["session"], table.extras["session"])
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].endswith(
        "two.csv: column session names 2 sessions (s1, s2); posecorr models one tracker frame and one mount for all "
        "rows: where the sessions' frames differ, fit each session's rows alone"), err
