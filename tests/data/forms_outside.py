"""Test-only effects outside the catalogue: the shapes a real tracker's error may take that
posecorr's catalogue does not hold. Written in plain numpy from their formulas alone (not from
posecorr.forms), to simulate sessions the diagnosis must see through.

c is the workspace centre (the context's c), d = p - c.
"""
import numpy as np
from scipy.spatial.transform import Rotation

from posecorr.effects import Effect, Param


def _matrix(theta, shape):
    return np.asarray(theta, float).reshape(shape)


class TrueStrain(Effect):
    """p <- c + (I + S)(p - c), S symmetric from its 6 entries (xx, yy, zz, xy, xz, yz)."""

    name = "true_strain"
    changes_rotation = False
    params = (Param("s", 6, (0.012, -0.008, 0.004, 0.006, -0.005, 0.003), 1e-2, "1"),)

    def forward(self, p, R, theta, ctx):
        xx, yy, zz, xy, xz, yz = np.asarray(theta, float)
        S = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
        return ctx.c + (p - ctx.c) @ (np.eye(3) + S).T, R


class TrueBend(Effect):
    """A bend of the space: p_z <- p_z + kz (dx^2 + dy^2), p_x <- p_x + kx dx dy (1/m)."""

    name = "true_bend"
    changes_rotation = False
    params = (Param("k", 2, (0.03, -0.02), 1e-2, "1/m"),)

    def forward(self, p, R, theta, ctx):
        kz, kx = np.asarray(theta, float)
        dx, dy = (p - ctx.c)[:, 0], (p - ctx.c)[:, 1]
        return p + np.stack([kx * dx * dy, 0.0 * dx, kz * (dx * dx + dy * dy)], axis=1), R


class TrueAttitudeBias(Effect):
    """p <- p + b (a . n) m: a bias along m (m) that grows with how far the tracker's z axis a
    leans towards n: a compliant mount sagging with the attitude."""

    name = "true_attitude_bias"
    changes_rotation = False
    params = (Param("b", 1, (0.004,), 1e-3, "m"),)

    def forward(self, p, R, theta, ctx):
        b = float(np.asarray(theta, float).reshape(-1)[0])
        n = np.array([0.6, 0.0, 0.8])
        m = np.array([0.0, 0.6, -0.8])
        return p + b * np.outer(R[:, :, 2] @ n, m), R


class TrueHeadingField(Effect):
    """R <- Rot_z(g . d) R: the heading turns by g . d rad over the workspace (rad/m)."""

    name = "true_heading_field"
    params = (Param("g", 3, (0.02, -0.015, 0.01), 1e-2, "rad/m"),)

    def forward(self, p, R, theta, ctx):
        g = np.asarray(theta, float)
        turns = Rotation.from_rotvec(np.outer((p - ctx.c) @ g, [0.0, 0.0, 1.0])).as_matrix()
        return p, turns @ R
