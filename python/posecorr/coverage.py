"""Which orientations a model was fitted on, and which poses lie beyond them.

The runtimes refuse a position outside the model's `input_bounds`, and accept every
orientation: a correction need not depend on orientation (the rigid fit, most physical
effects), and where it does, the orientation a tracker may take is the user's business. A
core fitted on the orientations of one session answers a pose turned away from all of them
with a guess, though: `20200717_Exp2` (nine poses within 0.4 degrees of one orientation)
gives a PMC that corrects its own poses to 5.3 mm and the same poses turned by 1, 2 and 5
degrees to 12, 37 and 204 mm. So an export whose core reads the orientation states the
cone of its training orientations (`KEY`: their mean and the largest angle from it), and
`apply` and the ROS 2 node count the poses more than `MARGIN` beyond it.

A cone about the mean is the coarsest bound that still tells one orientation from many: a
session turned about one axis only has a cone as wide as its turn about every axis.
"""
from __future__ import annotations

import json
import math
from typing import Any, Mapping, Sequence

import numpy as np

from .metrics import rotation_errors
from .rotations import REPRESENTATIONS, quat_to_matrix

KEY = "training_orientations"
# How far beyond the cone a pose may lie before it is counted: half the turn (1 deg) that took
# Exp2's PMC from 5.3 to 12 mm (above), about as wide as that session's own cone (0.44 deg).
MARGIN = np.deg2rad(0.5)


def cone(quaternions: np.ndarray) -> dict[str, Any]:
    """{"mean": [qw, qx, qy, qz], "within": rad}: the mean of unit quaternions (N, 4), sign
    free (the principal eigenvector of their scatter, the rotation nearest them all in the
    chordal sense), and the largest geodesic angle of any of them from it."""
    q = np.asarray(quaternions, float)
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    mean = np.linalg.eigh(q.T @ q)[1][:, -1]
    mean = mean if mean[0] >= 0 else -mean
    return {"mean": [float(v) for v in mean], "within": float(np.max(beyond_mean(q, mean)))}


def beyond_mean(quaternions: np.ndarray, mean: Any) -> np.ndarray:
    """(N,) geodesic angles (rad) of unit quaternions from `mean`."""
    return rotation_errors(quat_to_matrix(np.asarray(mean, float))[None], quat_to_matrix(np.asarray(quaternions, float)))


def stated(metadata: Mapping[str, str]) -> dict[str, Any] | None:
    """The cone a model's metadata states (`KEY`, as stored: JSON), or None: see `cone_of`."""
    try:
        return cone_of(json.loads(metadata.get(KEY, "null")))
    except ValueError:
        return None


def cone_of(value: Any) -> dict[str, Any] | None:
    """{"mean": (4,) array, "within": rad} of a decoded `KEY` value, or None where it is not a
    unit quaternion and an angle in [0, pi] given as numbers (a file of an older posecorr, or
    of another writer: it is a statement, and no runtime checks it)."""
    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    if not isinstance(value, Mapping):
        return None
    mean, within = value.get("mean"), value.get("within")
    if not (isinstance(mean, list) and len(mean) == 4 and all(map(number, mean)) and number(within)):
        return None
    mean = np.asarray(mean, float)
    if not np.all(np.isfinite(mean)) or abs(np.linalg.norm(mean) - 1.0) > 1e-6 or not 0.0 <= within <= np.pi:
        return None
    return {"mean": mean, "within": float(within)}


def reads_orientation(representation: Any) -> bool:
    """Whether a core of `representation` (the metadata's, decoded) reads the orientation:
    a PMC or an MLP on a representation of it, where a turn no training pose had is a guess."""
    codec = REPRESENTATIONS.get(representation) if isinstance(representation, str) else None
    return codec is not None and codec.orientation


class Beyond:
    """The poses, a table's chunk by chunk or a stream's one by one, that lie more than
    `MARGIN` beyond the training orientations of a model whose core reads them: counted, the
    first `shown` rows kept. A pose lies beyond where its angle from the mean exceeds
    `within` + `MARGIN`, compared as |q . mean| < cos of half that angle |q|: a few
    multiplications, for the ROS 2 node's every pose."""

    def __init__(self, metadata: Mapping[str, str], shown: int = 10) -> None:
        # a string is stored as itself (export.metadata.encode_value), the name of none as null
        self.cone = stated(metadata) if reads_orientation(metadata.get("representation")) else None
        self.shown, self.count, self.rows, self.largest = shown, 0, [], 0.0
        if self.cone is not None:
            edge = self.cone["within"] + MARGIN
            self._mean = [float(v) for v in self.cone["mean"]]
            self._cos = math.cos(0.5 * edge) if edge < np.pi else -1.0   # beyond pi: nothing lies beyond

    def add(self, quaternions: np.ndarray, rows: list[int], corrected: np.ndarray) -> None:
        """The unit quaternions (N, 4) of poses at the table's `rows`; those the model did not
        correct (`corrected` False: refused, a lost pose's zero quaternion) are not counted."""
        if self.cone is None:
            return
        q = np.asarray(quaternions, float)
        far = np.flatnonzero(corrected & (np.abs(q @ self._mean) < self._cos * np.linalg.norm(q, axis=1)))
        self.count += len(far)
        self.rows += [rows[i] for i in far[:self.shown - len(self.rows)]]
        if len(far):
            self.largest = max(self.largest, float(np.max(beyond_mean(q[far], self._mean))) - self.cone["within"])

    def one(self, q: Sequence[float]) -> bool:
        """Whether the unit quaternion `q` (w, x, y, z) of one pose lies beyond (the caller
        counts: the ROS 2 node over every model it serves)."""
        if self.cone is None:
            return False
        m = self._mean
        return abs(q[0] * m[0] + q[1] * m[1] + q[2] * m[2] + q[3] * m[3]) \
            < self._cos * math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])

    def record(self) -> dict[str, Any] | None:
        """{"count", "rows", "largest_rad", "within_rad", "margin_rad"}, or None where the
        model states no cone or its core does not read the orientation."""
        if self.cone is None:
            return None
        return {"count": self.count, "rows": self.rows, "largest_rad": self.largest,
                "within_rad": self.cone["within"], "margin_rad": float(MARGIN)}
