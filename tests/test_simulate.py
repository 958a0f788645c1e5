"""Geometry of the paper's setup and the simulator's tables, defaults and mix rule."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import polar
from scipy.spatial.transform import Rotation

from posecorr import effects, geometry
from posecorr.data import read_table, write_table
from posecorr.effects import get_effect, invert_effects
from posecorr.metrics import pose_metrics
from posecorr.simulate import DEFAULT_MIX, resolve_mix, simulate, simulate_session

DATA = Path(__file__).parent / "data"

# Raw rows of the paper's tables 2-4: rmse_pos (m), rmse_rot (rad).
PAPER_RAW = {1: (0.0440, None), 2: (0.0058, 0.0115), 3: (0.0222, 0.0508)}


# --- geometry -----------------------------------------------------------------------------

def test_station_pose_is_the_orthonormalised_eq23():
    R_S, t_S = geometry.station_pose()
    printed = geometry.PRINTED_BASE_T_STATION[:3, :3]
    np.testing.assert_allclose(R_S @ R_S.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(R_S) == pytest.approx(1.0, abs=1e-14)
    assert np.max(np.abs(R_S - printed)) < 1e-3            # 4-decimal rounding of the paper
    np.testing.assert_allclose(R_S, polar(printed)[0], atol=1e-12)   # nearest rotation (polar factor)
    np.testing.assert_array_equal(t_S, [0.0764, -1.5668, 0.6615])
    np.testing.assert_allclose(geometry.base_T_station()[:3, :3], R_S)


def test_end_T_tracker_and_eq19():
    np.testing.assert_array_equal(geometry.END_T_TRACKER[:3, 3], [0.0, 0.0, 0.042])
    exp = geometry.experiment(3)
    flange = exp.flange_poses()
    p, R = exp.reference_poses()
    # The tracker sits 42 mm along the flange z axis, same orientation.
    np.testing.assert_allclose(p, flange[:, :3, 3] + 0.042 * flange[:, :3, 2], atol=1e-15)
    np.testing.assert_allclose(R, flange[:, :3, :3], atol=1e-15)


@pytest.mark.parametrize("number, n, side, k", [(1, 1331, 0.4, 1), (2, 1625, 0.4, 13), (3, 3375, 0.2, 27)])
def test_lattices(number, n, side, k):
    exp = geometry.experiment(number)
    p, R = exp.reference_poses()
    assert exp.n_poses == n and p.shape == (n, 3) and R.shape == (n, 3, 3)
    np.testing.assert_allclose(p.min(0), geometry.WORKSPACE_CENTRE - side / 2, atol=1e-12)
    np.testing.assert_allclose(p.max(0), geometry.WORKSPACE_CENTRE + side / 2, atol=1e-12)
    np.testing.assert_allclose(p.mean(0), [0.0, -0.6, 0.5], atol=1e-12)
    assert len(np.unique(np.round(p, 9), axis=0)) == n // k
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-12)
    # every pose in front of the station (s_z < 0), about 1 m away
    R_S, t_S = geometry.station_pose()
    s = (p - t_S) @ R_S
    assert np.all(s[:, 2] < -0.7)
    assert exp.position_only == (number == 1)


def test_orientations():
    up = geometry.upright_rotation()
    np.testing.assert_allclose(up[:, 2], [0, 0, 1], atol=1e-15)        # tracker z up
    _, t_S = geometry.station_pose()
    to_station = (t_S - geometry.WORKSPACE_CENTRE)[:2]
    assert up[:2, 0] @ to_station / np.linalg.norm(to_station) == pytest.approx(1.0)   # x faces the station
    R2 = geometry.experiment(2).orientations
    yaws = Rotation.from_matrix(np.einsum("ji,njk->nik", up, R2)).as_rotvec()
    np.testing.assert_allclose(yaws[:, :2], 0.0, atol=1e-12)           # about the vertical only
    np.testing.assert_allclose(np.mod(yaws[:, 2], 2 * np.pi)[1:12], np.linspace(0, 2 * np.pi, 13)[1:12], atol=1e-12)
    R3 = geometry.experiment(3).orientations
    rel = Rotation.from_matrix(np.einsum("ji,njk->nik", up, R3)).as_euler("ZYX", degrees=True)
    assert sorted({tuple(np.round(r, 9)) for r in rel}) == sorted(
        {(y, p, r) for y in (-30.0, 0.0, 30.0) for p in (-30.0, 0.0, 30.0) for r in (-30.0, 0.0, 30.0)})


# --- default mix against the paper -------------------------------------------------------

@pytest.fixture(scope="module")
def sims() -> dict[tuple[int, int], object]:
    return {(n, seed): simulate(n, seed=seed) for n in (1, 2, 3) for seed in (0, 1234)}


@pytest.mark.parametrize("seed", [0, 1234])
@pytest.mark.parametrize("number", [1, 2, 3])
def test_default_mix_reproduces_paper_raw_rows(sims, number, seed):
    raw = sims[number, seed].raw
    pos, rot = PAPER_RAW[number]
    # within 0.9% on seven seeds; the paper prints 2-3 significant digits (0.0058 is +-0.9% by rounding)
    assert raw["rmse_pos"] == pytest.approx(pos, rel=0.02)
    if rot is None:
        assert raw["rmse_rot"] is None
    else:
        assert raw["rmse_rot"] == pytest.approx(rot, rel=0.02)


@pytest.mark.parametrize("number", [1, 2, 3])
def test_noise_floor_is_what_a_perfect_correction_leaves(sims, number):
    sim = sims[number, 0]
    assert sim.noise_floor["rmse_total"] < sim.raw["rmse_total"] / 10
    # Invert the systematic effects exactly (noise is not invertible: it stays in).
    mix = {k: v for k, v in sim.effects.items() if k != "noise"}
    table = sim.table
    p, R = invert_effects(table.meas_p, Rotation.from_quat(table.meas_q, scalar_first=True).as_matrix(),
                          mix, sim.context)
    corrected = np.concatenate([p, Rotation.from_matrix(R).as_quat(scalar_first=True)], axis=1)
    reference = table.reference if table.has_orientation else np.concatenate([table.ref_p, table.meas_q], 1)
    got = pose_metrics(reference, corrected, table.has_orientation)
    for key in ("rmse_pos", "rmse_rot", "rmse_total"):
        if sim.noise_floor[key] is not None:
            assert got[key] == pytest.approx(sim.noise_floor[key], rel=0.05)


def test_noise_floor_on_exp3_is_small_against_the_paper_best(sims):
    # the paper's best model leaves 4.2e-3 total on Exp III; the floor must sit well below it
    assert sims[3, 0].noise_floor["rmse_total"] < 2.5e-3


# --- the table ----------------------------------------------------------------------------

def test_table_layout(sims, tmp_path):
    sim1, sim3 = sims[1, 0], sims[3, 0]
    assert sim1.table.ref_q is None and sim3.table.ref_q is not None
    for sim, n in ((sim1, 1331), (sim3, 3375)):
        t = sim.table
        assert t.n == n
        np.testing.assert_allclose(np.linalg.norm(t.meas_q, axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(t.extras["t"], 10.0 * np.arange(1, n + 1))
        ids = t.extras["id"].astype(int)
        assert sorted(ids) == list(range(n)) and not np.all(np.diff(ids) > 0)   # shuffled
    # row k is lattice pose id[k]
    p, _ = geometry.experiment(3).reference_poses()
    np.testing.assert_array_equal(sim3.table.ref_p, p[sim3.table.extras["id"].astype(int)])
    assert not np.array_equal(sims[3, 0].table.extras["id"], sims[3, 1234].table.extras["id"])
    path = tmp_path / "exp1.csv"
    write_table(sim1.table, path)
    back = read_table(path)
    assert back.ref_q is None and back.n == 1331
    np.testing.assert_array_equal(back.meas_p, sim1.table.meas_p)


def test_measured_equals_chain_of_design_formulas():
    """base='none' with one effect: the table is that effect applied to the reference."""
    sim = simulate(3, effects="range_scale=0.01", base="none", order="lattice")
    _, t_S = geometry.station_pose()
    np.testing.assert_allclose(sim.table.meas_p, t_S + 1.01 * (sim.table.ref_p - t_S), atol=1e-14)
    np.testing.assert_allclose(np.abs(np.sum(sim.table.meas_q * sim.table.ref_q, axis=1)), 1.0, atol=1e-12)
    assert sim.noise_floor["rmse_total"] == 0.0
    np.testing.assert_array_equal(sim.table.extras["id"].astype(int), np.arange(3375))


def test_mix_rule():
    mix = resolve_mix(2, "range_scale=0.01;noise=off;incidence")
    assert list(mix) == ["mount", "sweep", "range_scale", "incidence", "drift", "station"]
    np.testing.assert_array_equal(mix["range_scale"], [0.01])
    np.testing.assert_array_equal(mix["incidence"], get_effect("incidence").default_theta())
    np.testing.assert_array_equal(mix["station"], DEFAULT_MIX[2]["station"])
    assert list(resolve_mix(1, {"station": np.zeros(6)}, base="none")) == ["station"]
    with pytest.raises(ValueError, match="base must be"):
        resolve_mix(1, None, base="other")
    with pytest.raises(ValueError, match="unknown experiment"):
        simulate(4)
    with pytest.raises(ValueError, match="'mount' takes 6 values"):
        simulate(1, effects="mount=1")


def test_default_mix_magnitudes_are_physical():
    for mix in DEFAULT_MIX.values():
        assert np.linalg.norm(mix["station"][:3]) < 0.03 and np.linalg.norm(mix["station"][3:]) < 0.05
        assert np.linalg.norm(mix["mount"][:3]) < 0.05 and np.linalg.norm(mix["mount"][3:]) < 0.01
        assert 0.001 <= mix["range_scale"][0] <= 0.01
        assert mix["noise"] == [3e-4, 5e-4, 2e-4]          # docs/design.md default noise
        assert 1800 <= mix["drift"][3] <= 4 * 3600


@pytest.fixture()
def user_effect_file():
    yield str(DATA / "example_effect.py")
    effects.unregister_effect("z_scale")


def test_user_effect_in_simulate(user_effect_file):
    base = simulate(1, base="none", order="lattice")
    sim = simulate(1, base="none", order="lattice", effect_files=[user_effect_file])
    assert list(sim.effects) == ["z_scale"]
    c = geometry.WORKSPACE_CENTRE
    k = get_effect("z_scale").default_theta()[0]
    np.testing.assert_allclose(sim.table.meas_p[:, 2], base.table.ref_p[:, 2] + k * (base.table.ref_p[:, 2] - c[2]))
    expected = np.sqrt(np.mean((k * (base.table.ref_p[:, 2] - c[2])) ** 2))
    assert sim.raw["rmse_pos"] == pytest.approx(expected, rel=1e-9)
    sim = simulate(1, effects="z_scale=off", effect_files=[user_effect_file])
    assert "z_scale" not in sim.effects and sim.effects_json()["station"]["v"] == DEFAULT_MIX[1]["station"][3:]


# --- realistic sessions with a clock --------------------------------------------------------

def test_a_session_with_a_duration_has_its_clock_and_its_drift():
    plain = simulate_session(4, n=20)
    timed = simulate_session(4, n=20, duration=800.0)
    assert plain.table.time() is None
    # Pose k at (k + 1) duration / n; the clock draws nothing, so the session is the same.
    np.testing.assert_allclose(timed.table.time(), 40.0 * np.arange(1, 21))
    np.testing.assert_array_equal(timed.table.measured, plain.table.measured)
    d, tau = np.array([4e-3, -2e-3, 3e-3]), 600.0
    drifting = simulate_session(4, n=20, duration=800.0, extra={"drift": [*d, tau]})
    # The drift acts in the cell (design: p + d (1 - exp(-t / tau))); the unknown station
    # frame turns it into the tracker's coordinates. Rows times R is R^T applied to each row.
    R_station = Rotation.from_rotvec(drifting.effects["station"][:3]).as_matrix()
    moved = (drifting.table.meas_p - timed.table.meas_p) @ R_station
    # atol: the range term of the noise sees the drifted position (k2 r^2, about 1e-5 m here)
    np.testing.assert_allclose(moved, np.outer(1.0 - np.exp(-timed.table.time() / tau), d), atol=5e-5)
    with pytest.raises(ValueError, match="duration"):
        simulate_session(4, n=20, duration=-1.0)
