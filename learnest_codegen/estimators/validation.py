"""The one set of checks every estimator, reference or compiled, applies to what it is given.

Shapes fail with :class:`~learnest_codegen.errors.ShapeError`, values (non-finite numbers, a
covariance that is not symmetric positive semidefinite) with
:class:`~learnest_codegen.errors.DataError`; both are ``ValueError``\\ s. Each message names the
call and the argument (``where``). A complex value is refused (its imaginary part would be
dropped silently by a float conversion).

Measurements may be missing: :func:`measurement` and ``run_arrays(..., missing=True)`` take NaN
in ``y`` as "no sample of this output" (the convention of :mod:`.contract`); an infinite ``y``
is still an error; :func:`measurements` turns them into validity flags (the C API's form).
Inputs go to the estimators' plausibility check (:mod:`.inputs`), so :func:`input_vector`
checks their shape only.
"""

from __future__ import annotations

import numpy as np

from ..errors import DataError, ShapeError
from ..runtime.limits import limit

#: Relative tolerance of the symmetry and semidefiniteness checks of a covariance.
COVARIANCE_RTOL = 1e-9


def real_array(where: str, value) -> np.ndarray:
    """``value`` as a float64 array; a complex or non-numeric value raises :class:`DataError`."""
    if np.iscomplexobj(value):
        raise DataError(f"{where}: expected real numbers, got complex values")
    kind = getattr(value, "dtype", None)
    if kind is None:
        try:
            kind = np.asarray(value).dtype
        except ValueError:  # ragged: the conversion below says so
            kind = np.dtype(object)
    if kind.kind in "OUSV":  # float() would make None a NaN (a missing output) and "1" a 1
        odd = [v for v in np.asarray(value, dtype=object).ravel()
               if v is None or isinstance(v, (str, bytes))]
        if odd:
            raise DataError(f"{where}: expected real numbers, got {odd[0]!r} (NaN marks a "
                            "missing value)")
    try:
        return np.ascontiguousarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise DataError(f"{where}: expected real numbers, got {type(value).__name__} ({exc})") from exc


def input_vector(where: str, value, n: int) -> np.ndarray:
    """``value`` as a float64 ``(n,)`` array; NaN and infinite entries pass (see :mod:`.inputs`)."""
    v = real_array(where, value)
    if v.shape != (n,):
        raise ShapeError(f"{where}: expected shape ({n},), got {v.shape}")
    return v


def vector(where: str, value, n: int) -> np.ndarray:
    """``value`` as a finite float64 ``(n,)`` array."""
    v = input_vector(where, value, n)
    if not np.all(np.isfinite(v)):
        raise DataError(f"{where}: non-finite value in {v}")
    return v


def measurement(where: str, value, n: int) -> np.ndarray:
    """``value`` as a float64 ``(n,)`` array in which NaN means missing; infinity raises."""
    v = input_vector(where, value, n)
    if np.any(np.isinf(v)):
        raise DataError(f"{where}: infinite value in {v} (NaN marks a missing output)")
    return v


def matrix(where: str, value, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``; the rows holding non-finite values are named."""
    a = real_array(where, value)
    if a.shape != tuple(shape):
        raise ShapeError(f"{where}: expected shape {tuple(shape)}, got {a.shape}")
    finite = np.isfinite(a)
    if not finite.all():
        rows = np.flatnonzero(~finite.reshape(a.shape[0], -1).all(axis=1))
        raise DataError(f"{where}: non-finite values in row(s) {rows[:5].tolist()}")
    return a


def covariance(where: str, value, n: int, *, definite: bool = False,
               precision: str | None = "float64") -> np.ndarray:
    """``value`` as a symmetric positive semidefinite ``(n, n)`` array (definite if asked).

    Symmetry and the smallest eigenvalue are judged relative to the largest diagonal entry
    (:data:`COVARIANCE_RTOL`): rounding passes, a real asymmetry or a negative direction not.
    With ``precision``, every variance must lie in that precision's range
    (``runtime/limits.py``, ``variance``; a semidefinite one may also be 0): the C checks the
    same. ``None`` skips it (an estimator's own covariance).
    """
    a = matrix(where, value, (n, n))
    scale = float(np.max(np.abs(np.diag(a)), initial=0.0)) or 1.0
    asym = float(np.max(np.abs(a - a.T), initial=0.0))
    if asym > COVARIANCE_RTOL * scale:
        raise DataError(f"{where}: a covariance must be symmetric; largest |A - A^T| is {asym:.3g}")
    smallest = float(np.linalg.eigvalsh((a + a.T) / 2)[0])
    if smallest < -COVARIANCE_RTOL * scale or (definite and smallest <= COVARIANCE_RTOL * scale):
        kind = "positive definite" if definite else "positive semidefinite"
        raise DataError(f"{where}: a covariance must be {kind}; its smallest eigenvalue is {smallest:.3g}")
    if precision is not None:
        _variances_in_range(where, a, definite, precision)
    return a


def _variances_in_range(where: str, a: np.ndarray, definite: bool, precision: str) -> None:
    lim = limit("variance", precision)
    for i, v in enumerate(np.diag(a)):
        if (v == 0 and not definite) or lim.contains(float(v)):
            continue
        allowed = lim.describe().replace("a number", "each variance")
        zero = "" if definite else " (or 0: an exactly known direction)"
        raise DataError(f"{where}: variance {v:.3g} (diagonal entry {i}) is outside the range a "
                        f"covariance takes in {precision}: give {allowed}{zero}")


def run_arrays(where: str, U, Y, nu: int, ny: int, *,
               missing: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """``U (T, nu)``, ``Y (T, ny)`` as float64 arrays with the same ``T >= 1``, finite unless
    ``missing``: then NaN in ``Y`` marks a missing output and ``U`` is left to the input check
    (an infinite ``Y`` still raises)."""
    U, Y = real_array(f"{where}: U", U), real_array(f"{where}: Y", Y)
    if U.ndim != 2 or Y.ndim != 2 or U.shape[1] != nu or Y.shape[1] != ny \
            or len(U) != len(Y) or len(Y) < 1:
        raise ShapeError(f"{where}: expected U (T, {nu}) and Y (T, {ny}) with T >= 1, "
                         f"got {U.shape} and {Y.shape}")
    checks = (("Y", Y, np.isinf),) if missing else (("U", U, _nonfinite), ("Y", Y, _nonfinite))
    for name, A, bad in checks:
        if np.any(bad(A)):
            row = int(np.argwhere(bad(A))[0, 0])
            raise DataError(f"{where}: {name} has a non-finite value at sample {row}")
    return np.ascontiguousarray(U), np.ascontiguousarray(Y)


def _nonfinite(a: np.ndarray) -> np.ndarray:
    return ~np.isfinite(a)


def flags(where: str, valid, shape: tuple[int, ...]) -> np.ndarray | None:
    """Per-output validity (True: the output holds a measurement) as a bool array of
    ``shape``, or None for "every output valid"; 0/1 numbers and bools are accepted."""
    if valid is None:
        return None
    v = np.asarray(valid)
    if v.shape != tuple(shape):
        raise ShapeError(f"{where}: expected shape {tuple(shape)}, got {v.shape}")
    if v.dtype != bool and not np.all((v == 0) | (v == 1)):
        raise DataError(f"{where}: validity flags must be 0/1 or bool, got {np.unique(v)[:5].tolist()}")
    return v.astype(bool)


def measurements(where: str, Y, valid, ny: int) -> tuple[np.ndarray, np.ndarray | None]:
    """``Y (ny,)`` or ``(T, ny)`` and its validity (True: the output holds a measurement).

    Without ``valid``, NaN marks a missing output (the run format's empty cell); with it, a
    missing output may hold anything. Missing outputs are returned as 0 (the compiled
    estimators never read them), the validity as None when every output is present. An
    infinite value, or a NaN marked valid, raises :class:`DataError`.
    """
    Y = np.array(real_array(where, Y))
    if Y.ndim not in (1, 2) or Y.shape[-1] != ny:
        raise ShapeError(f"{where}: expected shape ({ny},) or (T, {ny}), got {Y.shape}")
    mask = flags(f"{where} valid", valid, Y.shape)
    if mask is None:
        mask = ~np.isnan(Y)
    Y[~mask] = 0.0
    bad = ~np.isfinite(Y)
    if bad.any():
        if Y.ndim == 1:
            raise DataError(f"{where}: non-finite value in {Y} (NaN marks a missing output; "
                            "infinity, or NaN marked valid, is an error)")
        row = int(np.argwhere(bad)[0, 0])
        raise DataError(f"{where}: Y has a non-finite value at sample {row} (NaN marks a "
                        "missing output; infinity, or NaN marked valid, is an error)")
    return Y, (None if mask.all() else mask)
