"""The reference states a quadrotor flight's estimates are scored against, from Vicon position.

Velocity and acceleration are not measured: they are derivatives of a fit to the motion-capture
position. A fit over a long window attenuates fast motion (an order-2 fit over ``L`` seconds
keeps ``3 (sin x - x cos x) / x^3`` of a sinusoid's velocity, ``x = w L / 2``), so an estimator
that smooths as much looks better against it than one that is right. The studies therefore
score against several windows (:data:`REFERENCE_WINDOWS_S`) and against a velocity that needs
almost no smoothing (central differences over 0.1 s, :func:`central_velocity`).
"""

from __future__ import annotations

import numpy as np
from scipy.signal import savgol_filter

from ..errors import DataError

# The paper's baseline: "a window length of 150 and a polynomial of order 2" at ~100 Hz. We read
# 150 as samples (1.5 s; a window in seconds would be absurd at 150). scipy accepts even windows
# but then the fit is centred half a sample off the output sample, a 5 ms delay; 151 keeps it
# centred.
SAVGOL_WINDOW, SAVGOL_ORDER = 151, 2
#: Savitzky-Golay windows [s] of the reference states the studies score against: a claim must
#: hold at each, since a longer window attenuates fast motion (and rewards estimators that do).
REFERENCE_WINDOWS_S = (0.5, 1.0, 1.5, 3.0)
#: Half window [s] of the central-difference velocity reference (``cd_0.1s``).
CD_HALF_WINDOW_S = 0.05
#: The references of :func:`references`: what each is, for reports.
REFERENCES = {**{f"sg_{w:g}s": f"Vicon position; velocity and acceleration from a {w:g} s "
                              f"Savitzky-Golay fit (order 2)" for w in REFERENCE_WINDOWS_S},
              f"cd_{2 * CD_HALF_WINDOW_S:g}s": f"Vicon position; velocity by central differences over "
                                              f"{2 * CD_HALF_WINDOW_S:g} s (no acceleration)"}
def reference_states(position: np.ndarray, dt: float, window: int = SAVGOL_WINDOW,
                     order: int = SAVGOL_ORDER) -> np.ndarray:
    """The paper's baseline states ``[p, v, a]`` (T, 9) from Vicon position ``(T, 3)`` [m].

    ``p`` is the Vicon position itself; ``v`` and ``a`` are the first and second derivatives of
    a Savitzky-Golay fit (``window`` samples, polynomial ``order``; scipy's ``interp`` edges).
    The fit attenuates fast motion: for a sinusoid of ``w`` rad/s an order-2 fit over ``L``
    seconds keeps ``3 (sin(x) - x cos(x)) / x^3`` of the velocity, ``x = w L / 2`` (0.94 at
    1 rad/s, 0.79 at 2 rad/s for the 1.51 s default).
    """
    if position.ndim != 2 or position.shape[1] != 3:
        raise DataError(f"reference_states: expected position (T, 3), got {position.shape}")
    if window > position.shape[0]:
        raise DataError(f"reference_states: Savitzky-Golay window {window} is longer than the "
                        f"{position.shape[0]} samples")
    deriv = [savgol_filter(position, window, order, deriv=n, delta=dt, axis=0) for n in (1, 2)]
    return np.hstack([position, *deriv])


def central_velocity(position: np.ndarray, dt: float, half_window_s: float = CD_HALF_WINDOW_S) -> np.ndarray:
    """Velocity by central differences of position over ``+-half_window_s``, ``(T, 3)`` (NaN
    within the half window of either end): ``(p[k+m] - p[k-m]) / (2 m dt)``. Its error on the
    NanoBench flights: Vicon noise 0.04-0.1 mm gives 1e-3 m/s, the curvature of the fastest
    figure-eights a few 1e-3 m/s; against a quartic Savitzky-Golay fit over 0.31 s it differs
    by 1-2.6e-6 m^2/s^2 (MSE), against estimator errors of 5e-5 to 6e-4."""
    m = max(1, int(round(half_window_s / dt)))
    out = np.full_like(position, np.nan, dtype=float)
    if len(position) > 2 * m:
        out[m:-m] = (position[2 * m:] - position[:-2 * m]) / (2 * m * dt)
    return out


def references(position: np.ndarray, dt: float, windows_s=REFERENCE_WINDOWS_S) -> dict[str, np.ndarray]:
    """The reference states of a log's Vicon ``position (T, 3)``: per window of
    ``windows_s`` the Savitzky-Golay ``[p, v, a]`` (order 2, ``sg_<w>s``), and ``cd_0.1s``
    (position and central-difference velocity, no acceleration: NaN); see :data:`REFERENCES`."""
    out = {}
    for w in windows_s:
        n = int(round(w / dt))
        out[f"sg_{w:g}s"] = reference_states(position, dt, n + (n % 2 == 0), SAVGOL_ORDER)
    nan = np.full_like(position, np.nan, dtype=float)
    out[f"cd_{2 * CD_HALF_WINDOW_S:g}s"] = np.hstack([position, central_velocity(position, dt), nan])
    return out
