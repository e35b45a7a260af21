"""Reader of NanoBench Crazyflie flights (Vicon + onboard logs, one CSV per flight, ~100 Hz).

A flight CSV has one row per Vicon sample: ``t`` (absolute host time [s]), Vicon position
``px, py, pz`` [m] and attitude ``qx, qy, qz, qw`` (scalar last), the accelerometer
``imu_acc_x/y/z`` (specific force in g, body frame), motor PWM ``motor_motor_m1..m4``
(0-65535), the battery voltage ``pwr_pm_vbat`` [V] and the onboard EKF's
``est_stateEstimate_{x,y,z,vx,vy,vz,ax,ay,az}`` (world frame, m, m/s and m/s^2: its position
agrees with Vicon to a few cm; its acceleration is gravity-free). Beside it lies
``<name>_metadata.yaml`` (trajectory, speed, battery voltages); see ``../shared/data/README.md``.

:func:`read_flight` turns a flight into a :class:`Flight`:

1. **Timing.** The nominal period is the median sample interval. Jitter (the std of the
   intervals) is reported; a missing sample (an interval of up to ``max_gap_s``) is filled by
   resampling every channel onto the uniform grid (linear interpolation; the attitude by
   spherical linear interpolation). A longer gap raises :class:`~learnest_codegen.errors.DataError`.
2. **Trimming.** Take-off and landing are cut: the flight is the span in which the motors run
   and the vehicle is more than ``trim_height_m`` above the ground level (the median Vicon
   height of the motors-off samples at the start); of several such stretches (a touch-and-go:
   ``B2_circle_fast_rep1``) the longest. A flight whose onboard data turn
   implausible (a brown-out) ends 1 s before that.
3. **Run.** ``y = [p, a_world]`` with ``a_world = R(q) (9.81 acc_g) - [0, 0, 9.81]`` [m/s^2];
   ``u = [R(q) e3 * pwm, vbat]`` with ``pwm`` the mean motor PWM over 65535 (the inputs of
   :data:`~learnest_codegen.systems.quadrotor.QUADROTOR`).
4. **Held measurements.** A row whose Vicon position (all three coordinates) or accelerometer
   (all three axes) repeats the row before exactly is a held value, not a new sample: with
   ``held="missing"`` (the default) the grid sample nearest to it has that output missing
   (NaN), with ``held="hold"`` it is used as before. In the NanoBench files this finds 2 held
   positions in 17 flights (both outside the trimmed flights) and no held accelerometer row:
   the dataset interpolates its onboard streams onto the Vicon clock
   (its metadata counts e.g. 1,997 IMU rows for 2,725 Vicon rows) rather than holding them,
   so every accelerometer row is an interpolation of a ~73 Hz stream (``docs/reports/flights.md``).
   The inputs (motors, battery) are held as logged: that is what was applied.

:func:`reference_states` gives the paper's baseline states from Vicon position alone: the
position itself, and velocity and acceleration from a Savitzky-Golay filter.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation, Slerp

from ..data import Run
from ..errors import DataError, SettingsError

GRAVITY = 9.81  # [m/s^2], the constant the README's conversion uses
PWM_FULL = 65535.0
POSITION = ("px", "py", "pz")
QUATERNION = ("qx", "qy", "qz", "qw")
ACCEL = ("imu_acc_x", "imu_acc_y", "imu_acc_z")
MOTORS = tuple(f"motor_motor_m{i}" for i in range(1, 5))
VBAT = "pwr_pm_vbat"
ONBOARD = tuple(f"est_stateEstimate_{n}" for n in ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az"))
REQUIRED = ("t", *POSITION, *QUATERNION, *ACCEL, *MOTORS, VBAT, *ONBOARD)
#: Measured channel groups whose exact repeat marks a held (not re-sampled) value.
MEASURED = {"position": POSITION, "acceleration": ACCEL}
HELD = ("missing", "hold")

# The paper's baseline: "a window length of 150 and a polynomial of order 2" at ~100 Hz. We read
# 150 as samples (1.5 s; a window in seconds would be absurd at 150). scipy accepts even windows
# but then the fit is centred half a sample off the output sample, a 5 ms delay; 151 keeps it
# centred.
SAVGOL_WINDOW, SAVGOL_ORDER = 151, 2


@dataclass(frozen=True)
class Timing:
    """How regular a flight's time stamps were before resampling.

    Attributes
    ----------
    dt : nominal sample period [s] (median interval, rounded to 1 us).
    jitter : std of the sample intervals [s].
    gaps : intervals longer than 1.5 ``dt`` (missing samples), filled by resampling.
    longest_gap : the longest interval [s].
    """

    dt: float
    jitter: float
    gaps: int
    longest_gap: float


@dataclass(frozen=True)
class Flight:
    """One trimmed, uniformly sampled flight.

    Attributes
    ----------
    name : the CSV's stem, e.g. ``"B2_circle_fast_rep1"``.
    run : the quadrotor :class:`~learnest_codegen.data.Run` (``x`` is ``None``), ``t`` from 0.
    reference : (T, 9) Savitzky-Golay reference states ``[p, v, a]`` (:func:`reference_states`).
    onboard : (T, 9) the Crazyflie EKF's ``[p, v, a]`` (world frame).
    quaternion : (T, 4) Vicon attitude ``(qx, qy, qz, qw)``.
    vbat : (T,) battery voltage [V].
    timing : the time stamps' regularity (:class:`Timing`).
    trimmed : ``(first, last)`` sample indices of the flight in the resampled log.
    truncated : whether the flight was cut short at implausible accelerometer data.
    metadata : the ``_metadata.yaml`` beside the CSV as flat ``key: value`` strings (``{}``
        when absent).
    """

    name: str
    run: Run
    reference: np.ndarray
    onboard: np.ndarray
    quaternion: np.ndarray
    vbat: np.ndarray
    timing: Timing
    trimmed: tuple[int, int]
    truncated: bool = False
    metadata: dict = field(default_factory=dict)

    @property
    def duration(self) -> float:
        """Flight time after trimming [s]."""
        return float(self.run.t[-1] - self.run.t[0])


def list_flights(root: str | Path) -> list[Path]:
    """Flight CSVs under ``root`` (a ``nanobench`` folder, or a data root holding one), sorted."""
    root = Path(root)
    folder = root / "nanobench" if (root / "nanobench").is_dir() else root
    if not folder.is_dir():
        raise FileNotFoundError(f"no NanoBench folder at {root} (expected CSVs in it or in "
                                f"{root / 'nanobench'})")
    return sorted(p for p in folder.glob("*.csv") if p.is_file())


def read_table(path: str | Path) -> dict[str, np.ndarray]:
    """Read a flight CSV into ``column -> (N,) array``, checking columns and values."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"flight file {path} not found")
    with path.open(newline="") as fh:
        header = [h.strip() for h in next(csv.reader(fh), [])]
    if not header:
        raise DataError(f"{path}: empty file, expected a header with columns {list(REQUIRED)}")
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise DataError(f"{path}: missing columns {missing} (a NanoBench flight needs {list(REQUIRED)})")
    try:
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    except ValueError as exc:
        raise DataError(f"{path}: non-numeric or ragged content: {exc}") from exc
    if table.shape[0] < 2 or table.shape[1] != len(header):
        raise DataError(f"{path}: expected >= 2 rows of {len(header)} values, got shape {table.shape}")
    columns = {name: table[:, i] for i, name in enumerate(header)}
    for name in REQUIRED:
        bad = np.flatnonzero(~np.isfinite(columns[name]))
        if bad.size:
            raise DataError(f"{path}: non-finite value in column {name!r} at data row {bad[0] + 1} "
                            f"({bad.size} in that column)")
    return columns


def check_timing(t: np.ndarray, where: str, max_gap_s: float) -> Timing:
    """Check that ``t`` increases strictly with no gap longer than ``max_gap_s``."""
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise DataError(f"{where}: time must increase strictly; t[{k + 1}]={t[k + 1]!r} after "
                        f"t[{k}]={t[k]!r}")
    # The median interval, to the microsecond: absolute host times of ~1.7e9 s stored as
    # doubles carry ~1e-7 s of round-off, which must not make 0.01 s into 0.0099999905 s.
    dt = round(float(np.median(steps)), 6)
    longest = float(steps.max())
    if longest > max_gap_s:
        k = int(np.argmax(steps))
        raise DataError(f"{where}: gap of {longest:.3f} s after t={t[k] - t[0]:.3f} s (sample {k}); "
                        f"at most {max_gap_s} s can be filled (nominal period {dt:.4f} s)")
    return Timing(dt, float(np.std(steps)), int(np.sum(steps > 1.5 * dt)), longest)


def world_acceleration(quaternion: np.ndarray, acc_g: np.ndarray) -> np.ndarray:
    """``R(q) (9.81 acc_g) - [0, 0, 9.81]``: (T, 3) world acceleration [m/s^2] from (T, 4), (T, 3)."""
    return Rotation.from_quat(quaternion).apply(GRAVITY * acc_g) - np.array([0.0, 0.0, GRAVITY])


def thrust_vector(quaternion: np.ndarray, pwm: np.ndarray) -> np.ndarray:
    """``R(q) e3 * pwm``: (T, 3) world-frame thrust direction scaled by throttle (0-1)."""
    return Rotation.from_quat(quaternion).apply(np.array([0.0, 0.0, 1.0])) * pwm[:, None]


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


def read_metadata(path: Path) -> dict:
    """The flat ``key: value`` lines of a flight's ``_metadata.yaml`` (nested keys dotted)."""
    meta_path = path.with_name(f"{path.stem}_metadata.yaml")
    if not meta_path.is_file():
        return {}
    out, parent = {}, ""
    for line in meta_path.read_text().splitlines():
        if not line.strip() or ":" not in line:
            continue
        key, _, value = line.partition(":")
        nested = line.startswith(" ")
        if not nested:
            parent = key.strip() if not value.strip() else ""
        if value.strip():
            out[f"{parent}.{key.strip()}" if nested and parent else key.strip()] = value.strip()
    return out


def held_rows(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per measured group (:data:`MEASURED`): (N,) bool, the rows that repeat the row before."""
    out = {}
    for group, names in MEASURED.items():
        values = np.column_stack([columns[n] for n in names])
        out[group] = np.r_[False, np.all(np.diff(values, axis=0) == 0, axis=1)]
    return out


def _resample(t: np.ndarray, columns: dict[str, np.ndarray], dt: float,
              held: dict[str, np.ndarray] | None = None):
    """Every column on the uniform grid ``k dt`` from the first sample; quaternions by slerp.

    ``out["missing_<group>"]`` marks the grid samples whose nearest row is ``held`` in that
    group (the values themselves are interpolated as ever: trimming and the reference use
    them).
    """
    t = t - t[0]  # relative time: absolute host times would lose digits on the grid
    grid = dt * np.arange(int(np.floor(t[-1] / dt + 1e-6)) + 1)
    out = {name: np.interp(grid, t, values) for name, values in columns.items()}
    nearest = np.clip(np.searchsorted(t, grid), 1, len(t) - 1)
    nearest -= (grid - t[nearest - 1]) < (t[nearest] - grid)
    for group, rows in (held or {}).items():
        out[f"missing_{group}"] = rows[nearest]
    quat = np.stack([columns[n] for n in QUATERNION], axis=1)
    norms = np.linalg.norm(quat, axis=1)
    if np.any(np.abs(norms - 1.0) > 0.1):
        k = int(np.argmax(np.abs(norms - 1.0)))
        raise DataError(f"attitude quaternion at data row {k + 1} has norm {norms[k]:.3f}, expected 1")
    out["quaternion"] = Slerp(t, Rotation.from_quat(quat))(grid).as_quat()
    return grid, out


def airborne_span(height: np.ndarray, pwm: np.ndarray, trim_height_m: float) -> tuple[int, int]:
    """``(first, last)``: the longest stretch in which the motors run and the height is above
    the ground level (before the motors start) plus ``trim_height_m``."""
    start = int(np.argmax(pwm > 0))  # first sample with the motors running
    ground = float(np.median(height[:start])) if start > 0 else float(height[0])
    flying = np.concatenate([[0], ((pwm > 0) & (height > ground + trim_height_m)).astype(int), [0]])
    starts, ends = np.flatnonzero(np.diff(flying) == 1), np.flatnonzero(np.diff(flying) == -1)
    if starts.size == 0 or np.max(ends - starts) < 2:
        raise DataError(f"no airborne samples: the vehicle never rises {trim_height_m} m above the "
                        f"ground level {ground:.3f} m with the motors running")
    longest = int(np.argmax(ends - starts))  # a touch-and-go at the end is not part of the flight
    return int(starts[longest]), int(ends[longest]) - 1


def read_flight(path: str | Path, *, trim: bool = True, trim_height_m: float = 0.15,
                max_gap_s: float = 0.05, max_accel_mps2: float = 20.0,
                savgol_window: int = SAVGOL_WINDOW, savgol_order: int = SAVGOL_ORDER,
                held: str = "missing") -> Flight:
    """Read a NanoBench flight CSV into a trimmed, uniformly sampled :class:`Flight`.

    Parameters
    ----------
    path : the flight's CSV.
    trim : cut take-off and landing (see the module docstring).
    trim_height_m : height above the ground level that counts as airborne [m]. 0.15 m cuts
        the touchdown: at 0.05 m, four of the 17 NanoBench flights end with a 30-60 m/s^2
        landing impact.
    max_accel_mps2 : an accelerometer-derived acceleration above this [m/s^2] marks the end
        of usable data (``B2_circle_medium_rep3``: at 28.5 s, 1 m up, the battery browns out,
        the accelerometer reads > 100 m/s^2 and the onboard EKF diverges); the flight ends 1 s
        before it. ``truncated`` records it.
    max_gap_s : the longest sample interval that is filled by resampling [s].
    savgol_window, savgol_order : the reference filter (:func:`reference_states`); it runs on
        the whole log before trimming, so the trimmed flight has no filter edge inside.
    held : ``"missing"``: a held position or accelerometer value is a missing output (NaN);
        ``"hold"``: it is used as a sample (see the module docstring, step 4).

    Raises
    ------
    DataError : missing columns, non-numeric or non-finite values, time not increasing, a gap
        longer than ``max_gap_s``, a bad quaternion, no airborne part.
    """
    if held not in HELD:
        raise SettingsError(f"read_flight: held must be one of {HELD}, got {held!r}")
    path = Path(path)
    columns = read_table(path)
    t = columns.pop("t")
    timing = check_timing(t, str(path), max_gap_s)
    t, c = _resample(t, columns, timing.dt, held_rows(columns) if held == "missing" else None)
    quat = c["quaternion"]
    pwm = np.mean([c[m] for m in MOTORS], axis=0) / PWM_FULL
    position = np.stack([c[n] for n in POSITION], axis=1)
    try:
        first, last = airborne_span(position[:, 2], pwm, trim_height_m) if trim else (0, len(t) - 1)
        reference = reference_states(position, timing.dt, savgol_window, savgol_order)
    except DataError as exc:
        raise DataError(f"{path}: {exc}") from exc
    acc = world_acceleration(quat, np.stack([c[n] for n in ACCEL], axis=1))
    implausible = np.flatnonzero(np.linalg.norm(acc[first:last + 1], axis=1) > max_accel_mps2)
    if implausible.size:  # a brown-out or sensor failure: keep what comes before, less 1 s
        last = first + int(implausible[0]) - int(round(1.0 / timing.dt))
        if last - first < 2 * savgol_window:
            raise DataError(f"{path}: the accelerometer exceeds {max_accel_mps2} m/s^2 "
                            f"{implausible[0] * timing.dt:.2f} s into the flight; too little is left")
    u = np.hstack([thrust_vector(quat, pwm), c[VBAT][:, None]])
    y = np.hstack([position, acc])
    for group, block in (("position", slice(0, 3)), ("acceleration", slice(3, 6))):
        if f"missing_{group}" in c:
            y[c[f"missing_{group}"], block] = np.nan
    sl = slice(first, last + 1)
    run = Run(t[sl] - t[first], u[sl], y[sl], None, "quadrotor")
    onboard = np.stack([c[n] for n in ONBOARD], axis=1)
    return Flight(path.stem, run, reference[sl], onboard[sl], quat[sl], c[VBAT][sl], timing,
                  (first, last), bool(implausible.size), read_metadata(path))
