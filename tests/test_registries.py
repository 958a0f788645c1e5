"""Registries: a representation added by registering it alone works end to end."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from posecorr import rotations
from posecorr._xp import namespace


def _matrix_to_mrp(R):
    """Modified Rodrigues parameters q_xyz / (1 + q_w) (q_w >= 0 from matrix_to_quat)."""
    q = rotations.matrix_to_quat(R)
    return q[..., 1:4] / (1.0 + q[..., 0:1])


def _mrp_to_matrix(p):
    xp = namespace(p)
    n2 = xp.sum(p * p, axis=-1, keepdims=True)
    q = xp.concat([1.0 - n2, 2.0 * p], axis=-1) / (1.0 + n2)
    return rotations.quat_to_matrix(q)


@pytest.fixture
def mrp():
    rotations.register_representation("mrp", rotations.Representation(3, _matrix_to_mrp, _mrp_to_matrix))
    yield "mrp"
    del rotations.REPRESENTATION_CODECS["mrp"], rotations.REPRESENTATIONS["mrp"]


def test_registered_representation_round_trips_against_scipy(mrp: str) -> None:
    R = Rotation.random(1000, random_state=0)
    params = rotations.encode(R.as_matrix(), mrp)
    assert np.allclose(params, R.as_mrp(), atol=1e-12)       # scipy's shortest MRP: q_w >= 0 too
    assert np.allclose(rotations.decode(params, mrp), R.as_matrix(), atol=1e-12)


def test_registered_representation_fits_and_exports(mrp: str, tmp_path) -> None:
    """PMC on the new representation fits a simulated experiment and exports a graph that
    onnxruntime runs like predict: nothing but the registration was added."""
    from posecorr.export.parity import run_onnx
    from posecorr.simulate import simulate
    from posecorr.train import PMC

    table = simulate(3, seed=0).table.subset(np.arange(600))
    model = PMC(representation=mrp).fit(table.measured, table.reference)
    predicted = model.predict(table.measured)
    raw_rot = rotations.geodesic_angle(rotations.quat_to_matrix(table.measured[:, 3:7]),
                                       rotations.quat_to_matrix(table.reference[:, 3:7]))
    fit_rot = rotations.geodesic_angle(rotations.quat_to_matrix(predicted[:, 3:7]),
                                       rotations.quat_to_matrix(table.reference[:, 3:7]))
    assert np.sqrt(np.mean(fit_rot ** 2)) < 0.1 * np.sqrt(np.mean(raw_rot ** 2))
    exported = model.to_onnx(tmp_path / "mrp.onnx", measured=table.measured, reference=table.reference)
    assert exported["parity"]["passed"]
    onnx_out = run_onnx(str(tmp_path / "mrp.onnx"), table.measured)
    assert np.allclose(onnx_out[:, :3], predicted[:, :3], atol=1e-5)


def test_unknown_representation_is_refused_not_decoded_as_another() -> None:
    with pytest.raises(ValueError, match="unknown representation 'zhuo'"):
        rotations.decode(np.zeros((1, 6)), "zhuo")
