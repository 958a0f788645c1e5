"""An example user effect: the file a user passes with --effect-file.

`z_scale`: the station's vertical sweep is scaled about the workspace centre,
p_z <- p_z + k (p_z - c_z), k dimensionless. Written against the array namespace so that it
runs on numpy, torch and the ONNX exporter; inverted by the base class's fixed-point steps.
"""
from posecorr._xp import namespace
from posecorr.effects import Effect, Param


class ZScale(Effect):
    name = "z_scale"
    order = 5.5  # after drift, before the station registration
    changes_rotation = False  # R passes through: the generic inverse need not iterate on it
    params = (Param("k", 1, (0.01,), 1e-2, "1", doc="vertical scale error"),)

    def forward(self, p, R, theta, ctx):
        xp = namespace(p, R, theta)
        k = theta[..., 0]
        z = p[..., 2] + k * (p[..., 2] - xp.const(ctx.c, p)[..., 2])
        return xp.stack([p[..., 0], p[..., 1], z], axis=-1), R
