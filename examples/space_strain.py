"""An error outside the catalogue: the tracking space is strained.

Base stations whose registered geometry is slightly wrong (their distance, or the angle
between them) solve positions in a space that is stretched along some directions and
squeezed along others about the middle of the workspace:

    p <- c + (I + S)(p - c),  S symmetric (about 1 %)

c the workspace centre. A uniform S would be the catalogue's range scale; this one is not.
Used by examples/loop.sh to make a session whose error the catalogue cannot name.
"""
import numpy as np

from posecorr.effects import Effect, Param


class SpaceStrain(Effect):
    name = "space_strain"
    changes_rotation = False
    params = (Param("s", 6, (0.012, -0.008, 0.004, 0.006, -0.005, 0.003), 1e-2, "1",
                    doc="S entries xx, yy, zz, xy, xz, yz"),)

    def forward(self, p, R, theta, ctx):
        xx, yy, zz, xy, xz, yz = np.asarray(theta, float)
        S = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]])
        return ctx.c + (p - ctx.c) @ (np.eye(3) + S).T, R
