"""An error outside the catalogue: the tracking space is strained.

Base stations whose registered geometry is slightly wrong (their distance, or the angle
between them) solve positions in a space that is stretched along some directions and
squeezed along others about the middle of the workspace:

    p <- c + (I + S)(p - c),  S symmetric (about 1 %)

c the workspace centre. A uniform S would be the catalogue's range scale; this one is not.
Used by examples/loop.sh to make a session whose error the catalogue cannot name.
"""
from posecorr.effects import Effect, Param, to_namespace


class SpaceStrain(Effect):
    name = "space_strain"
    changes_rotation = False
    params = (Param("s", 6, (0.012, -0.008, 0.004, 0.006, -0.005, 0.003), 1e-2, "1",
                    doc="S entries xx, yy, zz, xy, xz, yz"),)

    def forward(self, p, R, theta, ctx):
        # Written with the arguments' array namespace (numpy, torch or the ONNX exporter's
        # symbolic tensors), not numpy's functions: so the map also fits and exports.
        xp, p, R, theta = to_namespace(p, R, theta)
        xx, yy, zz, xy, xz, yz = (theta[..., k] for k in range(6))
        rows = ((1 + xx, xy, xz), (xy, 1 + yy, yz), (xz, yz, 1 + zz))
        stretch = xp.stack([xp.stack(list(row), axis=-1) for row in rows], axis=-2)   # I + S
        c = xp.const(ctx.c, p)
        return c + xp.matmul(p - c, xp.swap_last(stretch)), R
