"""A user effect outside the catalogue: a periodic error of the horizontal sweep angle.

A Lighthouse rotor that wobbles once per sync period, or a slightly eccentric lens, bends
the horizontal sweep angle by a small periodic term in the angle itself:

    alpha' = alpha + a_s sin(k alpha) + a_c cos(k alpha)

with alpha = atan2(s_x, -s_z) the azimuth in the station frame (s = R_S^T (p - t_S)), k the
number of cycles per radian, and a_s, a_c (rad) the amplitudes (linear in the error, zero =
identity, which suits the fit and the score test). Orientation is untouched.

Use it with `--effect-file examples/periodic_sweep.py` on simulate, fit, diagnose, report.
"""
from posecorr._xp import namespace
from posecorr.effects import Effect, Param, from_station, station_coords, sweep_direction

CYCLES_PER_RAD = 60.0   # one period every 6 degrees of azimuth


class PeriodicSweep(Effect):
    name = "periodic_sweep"
    order = 2.5            # with the sweep, before the range scale
    changes_rotation = False
    params = (Param("a_s", 1, (4e-4,), 1e-4, "rad", doc="sine amplitude of the azimuth error"),
              Param("a_c", 1, (-3e-4,), 1e-4, "rad", doc="cosine amplitude of the azimuth error"))

    def forward(self, p, R, theta, ctx):
        xp = namespace(p, R, theta)
        s = station_coords(p, ctx)
        alpha = xp.atan2(s[..., 0], -s[..., 2])
        beta = xp.atan2(s[..., 1], -s[..., 2])
        r = xp.sqrt(xp.sum(s * s, axis=-1, keepdims=True))
        bent = alpha + theta[..., 0] * xp.sin(CYCLES_PER_RAD * alpha) + theta[..., 1] * xp.cos(CYCLES_PER_RAD * alpha)
        return from_station(r * sweep_direction(xp, bent, beta), ctx), R
