"""The noise floor: what residual a perfect prior would leave on these data.

What residual would a *perfect* prior leave? With truth, only the integrator's error: the floor
is a relative tolerance, ``relative_floor`` times the RMS of the prior's derivative. With
observer output, the observer's errors ``e_k``: ``r_k ~ (e_{k+1} - e_k) / dt``. The observer's
marginal variances bound this only if its errors were independent from sample to sample,
``(var_k + var_{k+1}) / dt^2`` (reported as ``floor_independent``); a smoother's errors are
strongly correlated, so that bound is far too high (cartpole: 12 m/s^2 for the cart against a
true gap of about 1 m/s^2) and useless as a threshold. The floor is therefore *measured* by a
calibration on the data's own trajectory (:func:`calibration`): synthetic measurements of the
observed trajectory, through the same observer, give per state the residual RMS ``sigma_s`` a
perfect model would leave at the data's speeds and inputs, and per effect what its feature can
"explain" of pure observer error (observer artefacts correlate with the state: a smoother lags
in hard accelerations). A calibration on a separately *simulated* run of the exact prior was
tried first and rejected: the simulated run's speeds need not resemble the data's (the ground
robot's excitation feeds the true drag forward, so an exact-prior run speeds up to 6.5 m/s,
where the observer's speed error is twice as large, which hid the real 1.05-C_D drag below the
floor). When the calibration fails, the floor falls back to the white part of the residual (the
MAD of its first differences), and the report says so.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from ..data import Run
from ..errors import DataError
from ..systems import System
from .blur import run_blur
from .effects import Effect
from .fit import Pairs, one_step
from .segments import Segment
from .settings import DiagnosisSettings


def calibration(system: System, effects: Sequence[Effect], segments: Sequence[Segment],
                settings: DiagnosisSettings) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Noise floor of the observer on the data's own trajectory (see the module docstring).

    The data's state observations ``z`` are taken as a true trajectory; it is exactly the
    trajectory of the prior plus a known, time-indexed derivative correction ``d_k`` (the prior's
    residual along ``z``). Synthetic measurements ``h(z) + noise`` (the system's measurement
    noise) go through the same observer; the residual of "prior + d_k" on its output is then pure
    observer error, at the data's own speeds, accelerations and inputs. Returns the per-state RMS
    ``(nx,)`` of that residual, its features ``(N, nx, m)``, the residual ``(N, nx)`` and the
    segment of each row ``(N,)``.
    """
    rng = np.random.default_rng(settings.seed + 7_777)
    from ..observers import observe

    rs, Js, labels = [], [], []
    for n, seg in enumerate(segments):
        run = seg.run
        y = np.asarray(system.h(seg.z, run.u))
        y = y + rng.normal(size=y.shape) * np.asarray(system.noise.measurement_std)
        synthetic = Run(run.t, run.u, y, seg.z, run.system)
        seen = observe(synthetic, system, settings.observer)
        chains = run_blur(system, len(run), float(np.median(np.diff(run.t))), seen.method, seen.info)
        on_truth = Pairs.from_states([(run.t, seg.z, run.u)])
        on_observed = Pairs.from_states([(run.t, seen.zeta, run.u, chains)])
        known, _ = one_step(system, effects, np.zeros(len(effects)), on_truth, with_features=False)
        r, J = one_step(system, effects, np.zeros(len(effects)), on_observed)
        if len(on_truth) == len(run) - 1:  # the known correction as the observer sees it
            for c in chains:
                known[:, c.state] = c.apply((known[:, c.state] * on_truth.dt)[:, None])[:, 0] / on_truth.dt
        diff = r - known
        for name in system.periodic_states:  # residuals are rates; wrap their step-sized parts
            i = system.state_names.index(name)
            diff[:, i] = np.angle(np.exp(1j * diff[:, i] * on_truth.dt)) / on_truth.dt
        rs.append(diff)
        Js.append(J)
        labels.append(np.full(len(diff), n))
    r, J = np.concatenate(rs), np.concatenate(Js)
    if not np.isfinite(r).all():
        raise DataError("calibration residual is not finite")
    return np.sqrt(np.mean(r**2, axis=0)), J, r, np.concatenate(labels)


def white_floor(r: np.ndarray) -> np.ndarray:
    """(nx,) std of the white part of a residual: 1.4826 MAD of its first differences / sqrt 2."""
    d = np.diff(r, axis=0)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / np.sqrt(2.0)


def derivative_scale(system: System, pairs: Pairs) -> np.ndarray:
    """(nx,) RMS of the prior's derivative over the data: the scale of "how fast a state moves"."""
    f = np.asarray(system.f(pairs.x, pairs.u))
    return np.sqrt(np.mean(f**2, axis=0))


def noise_floor(system: System, effects: Sequence[Effect], segments: Sequence[Segment], pairs: Pairs,
                r0: np.ndarray, source: str, settings: DiagnosisSettings):
    """``(sigma (nx,), method, spurious (m,) or None, error)``: the floor per state, how it
    was found, what each effect's feature explains of pure observer error (weighted, noise units),
    and that error itself with every feature at the prior (a :class:`~learnest_codegen.diagnosis.cv.
    FitData` of the residual states, weighted; ``None`` without a calibration run), on which the
    selection measures what a delay or a lag fitted like the data's would find in the observer's
    error alone."""
    from .cv import single_feature_size, weighted

    scale = derivative_scale(system, pairs)
    method, cal, sigma_cal = "relative", None, np.zeros(system.nx)
    if source == "observer" and settings.calibrate:
        try:
            sigma_cal, J_cal, r_cal, runs_cal = calibration(system, effects, segments, settings)
            method = "calibration (the observer on synthetic measurements of the data's trajectory)"
            cal = (J_cal, r_cal, runs_cal)
        except Exception as exc:  # noqa: BLE001 - an observer that fails here; fall back, say so
            sigma_cal = white_floor(r0)
            method = f"white part of the residual (calibration failed: {exc!r})"
    elif source == "observer":
        sigma_cal, method = white_floor(r0), "white part of the residual"
    sigma = np.maximum(np.maximum(sigma_cal, settings.relative_floor * scale), 1e-12)
    rows = [system.state_names.index(s) for s in system.residual_state_names]
    error = weighted(cal[1], cal[0], rows, sigma[rows], runs=cal[2]) if cal is not None else None
    spurious = single_feature_size(error) if error is not None else None
    return sigma, method, spurious, error
