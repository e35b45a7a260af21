"""The checks a quadrotor flight log passes (``recordings/crazyflie.py`` runs them).

Each returns a per-sample mask of the samples it finds faulty, on the flight's uniform grid,
and the :class:`~.checks.Finding` of each faulty span; the reader then keeps the longest
airborne stretch free of every fault (or leaves the flight out when too little is left).

* :func:`accelerometer_faults`: the world-frame accelerometer against the second derivative of
  the motion-capture position. On the 17 NanoBench flights their difference, averaged over
  0.5 s, stays within 1.25 m/s^2 of its flight's median (the median itself, 0.1-0.5 m/s^2, is
  the accelerometer's constant offset, which the estimators with offset states model); a
  faulty accelerometer (a reading that climbs to several g while the vehicle flies normally,
  a brown-out) leaves that band. The span starts where a hinge fit dates the drift's onset
  (:func:`~.checks.drift_onset`), not where it crosses the threshold, and the flight ends
  ``margin_s`` before it.
* :func:`input_faults`: motor PWM and thrust commands outside ``0..65535``.
* :func:`dropout_mask`: the grid samples inside a gap of the log longer than can be bridged,
  widened by half the longest reference window (the reference fits across the gap would
  mix both sides).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.signal import savgol_filter

from .checks import Finding, drift_onset, grow, runs_of

#: The 0.5 s mean of (accelerometer - motion-capture acceleration) may leave its flight's
#: median by this much [m/s^2] before the span counts as an accelerometer fault. The clean
#: NanoBench flights stay within 1.25 m/s^2.
ACCEL_FAULT_MPS2 = 2.0
#: The largest plausible offset [m/s^2]: the clean flights' 0.5 s means stay within 0.9 of
#: zero 99 % of the time; the offset is the median of the samples within this of zero.
OFFSET_MAX_MPS2 = 1.0
#: The mean's window [s], and the motion-capture second derivative's (a cubic
#: Savitzky-Golay fit: 1 mm of position noise reads 0.05 m/s^2 at 0.31 s).
ACCEL_MEAN_S, ACCEL_VICON_S = 0.5, 0.31
#: How far back the onset of a drift is looked for [s], and the margin kept before it [s].
DRIFT_LOOKBACK_S, MARGIN_S = 30.0, 1.0
#: Spans over the threshold less than this apart [s] are one fault (a drift crossing back and
#: forth on its noise).
MERGE_S = 2.0
PWM_RANGE = (0.0, 65535.0)


def _odd(samples: float) -> int:
    n = max(3, int(round(samples)))
    return n + (n % 2 == 0)


def accelerometer_faults(name: str, accel: np.ndarray, position: np.ndarray, dt: float,
                         span: tuple[int, int], threshold: float = ACCEL_FAULT_MPS2,
                         margin_s: float = MARGIN_S) -> tuple[np.ndarray, list[Finding]]:
    """``(faulty, findings)``: the samples (of the whole log) within the airborne ``span``
    whose accelerometer disagrees with the motion capture (see the module docstring).

    ``accel`` and ``position`` are the log's world acceleration [m/s^2] and position [m],
    ``(T, 3)`` on the grid of period ``dt``."""
    first, last = span
    faulty = np.zeros(len(accel), bool)
    window = _odd(ACCEL_VICON_S / dt)
    if last - first + 1 < 2 * window:
        return faulty, []
    vicon = savgol_filter(position, window, 3, deriv=2, delta=dt, axis=0)
    diff = uniform_filter1d(accel - vicon, _odd(ACCEL_MEAN_S / dt), axis=0)[first:last + 1]
    # the offset: the median over the samples within OFFSET_MAX of zero (a drift of several
    # g over most of a flight would drag a plain median), refined over those not found faulty
    good = np.linalg.norm(diff, axis=1) <= OFFSET_MAX_MPS2
    if not good.any():
        good = np.ones(len(diff), bool)
    for _ in range(3):
        deviation = np.linalg.norm(diff - np.median(diff[good], axis=0), axis=1)
        over = deviation > threshold
        if not over.any() or over.all() or np.array_equal(good, ~over):
            break
        good = ~over
    if not over.any():
        return faulty, []
    findings = []
    lookback, margin = int(round(DRIFT_LOOKBACK_S / dt)), int(round(margin_s / dt))
    for start, end in runs_of(grow(over, 0, int(round(MERGE_S / dt)))):
        end = min(end, len(over) - 1)
        end = start + int(np.flatnonzero(over[start:end + 1])[-1])
        onset = drift_onset(deviation, start, lookback)
        lo = max(0, onset - margin)
        faulty[first + lo:first + end + 1] = True
        peak = start + int(np.argmax(deviation[start:end + 1]))
        findings.append(Finding(name, "accelerometer", (first + onset) * dt, (first + end) * dt,
                                f"disagrees with the motion capture's acceleration by up to "
                                f"{deviation[peak]:.1f} m/s^2 (0.5 s mean, beyond its flight's "
                                f"offset; threshold {threshold:g}) from {(first + onset) * dt:.2f} s, "
                                f"over {threshold:g} at {(first + start) * dt:.2f} s", "cut"))
    return faulty, findings


def input_faults(name: str, rows_t: np.ndarray, columns: dict[str, np.ndarray], grid: np.ndarray,
                 names: tuple[str, ...]) -> tuple[np.ndarray, list[Finding]]:
    """``(faulty, findings)``: grid samples next to a logged row whose value of one of
    ``names`` (motor PWM, thrust command) lies outside ``0..65535``; ``rows_t`` are the rows'
    times (from 0), ``grid`` the grid's."""
    lo, hi = PWM_RANGE
    bad_rows = np.zeros(len(rows_t), bool)
    worst = {}
    for column in names:
        if column not in columns:
            continue
        values = columns[column]
        out = (values < lo) | (values > hi)
        if out.any():
            bad_rows |= out
            worst[column] = (float(values.min()), float(values.max()), int(out.sum()))
    faulty = np.zeros(len(grid), bool)
    if not bad_rows.any():
        return faulty, []
    # a grid sample is faulty if a faulty row lies within one interval of it
    indicator = np.interp(grid, rows_t, bad_rows.astype(float))
    faulty = indicator > 0
    detail = "; ".join(f"{c} {n} value(s) outside {lo:.0f}..{hi:.0f} (from {a:.0f} to {b:.0f})"
                       for c, (a, b, n) in worst.items())
    findings = [Finding(name, "inputs", grid[a], grid[b], detail, "cut") for a, b in runs_of(faulty)]
    return faulty, findings


def dropout_mask(name: str, rows_t: np.ndarray, grid: np.ndarray, max_gap_s: float, widen_s: float,
                 dropped_rows: int = 0) -> tuple[np.ndarray, list[Finding]]:
    """``(faulty, findings)``: grid samples inside a gap of more than ``max_gap_s`` between
    logged rows (times ``rows_t`` from 0), each gap widened by ``widen_s`` on both sides;
    ``dropped_rows`` (rows left out for non-finite values) is named in the findings."""
    steps = np.diff(rows_t)
    faulty = np.zeros(len(grid), bool)
    gaps = np.flatnonzero(steps > max_gap_s)
    for k in gaps:
        faulty |= (grid > rows_t[k]) & (grid < rows_t[k + 1])
    if not gaps.size:
        return faulty, ([Finding(name, "dropout", None, None, f"{dropped_rows} row(s) with non-finite "
                                 "values left out", "kept", "bridged by resampling")]
                        if dropped_rows else [])
    dt = float(np.median(np.diff(grid)))
    widen = int(round(widen_s / dt))
    core = faulty
    faulty = grow(core, widen, widen)
    extra = f" ({dropped_rows} row(s) with non-finite values left out)" if dropped_rows else ""
    findings = [Finding(name, "dropout", rows_t[k], rows_t[k + 1],
                        f"no data for {steps[k]:.3f} s (at most {max_gap_s:g} s is bridged){extra}",
                        "cut", f"{widen_s:g} s either side: the references fit across it")
                for k in gaps]
    return faulty, findings
