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
   spherical linear interpolation). A longer gap, or a row with a non-finite value, is a
   dropout: the flight is cut there (step 2).
2. **Trimming and checks.** Take-off and landing are cut: the flight is the span in which the
   motors run and the vehicle is more than ``trim_height_m`` above the ground level (the
   median Vicon height of the motors-off samples at the start); of several such stretches (a
   touch-and-go: ``B2_circle_fast_rep1``) the longest. The checks of
   :mod:`~.flight_checks` find faulty spans (an accelerometer that leaves the motion
   capture's acceleration, motor or thrust values outside 0-65535, dropouts); the flight is
   the longest airborne stretch free of them, and each is a :class:`~.checks.Finding` in
   ``Flight.findings`` (the callers print them and list them in their reports). A flight with
   less than ``min_flight_s`` left is refused (:class:`DataError` naming the findings).
3. **Run.** ``y = [p, a_world]`` with ``a_world = R(q) (9.81 acc_g) - [0, 0, 9.81]`` [m/s^2];
   ``u = [R(q) e3 * pwm, vbat]`` with ``pwm`` the mean motor PWM over 65535 (the inputs of
   :data:`~learnest_codegen.systems.quadrotor.QUADROTOR`).
4. **Held measurements.** A row whose Vicon position (all three coordinates) or accelerometer
   (all three axes) repeats the row before exactly is a held value, not a new sample: with
   ``held="missing"`` (the default) the grid sample nearest to it has that output missing
   (NaN), with ``held="hold"`` it is used as a sample. In the NanoBench files this finds 2 held
   positions in 17 flights (both outside the trimmed flights) and no held accelerometer row:
   the dataset interpolates its onboard streams onto the Vicon clock
   (its metadata counts e.g. 1,997 IMU rows for 2,725 Vicon rows) rather than holding them,
   so every accelerometer row is an interpolation of a ~73 Hz stream (``docs/reports/flights.md``).
   The inputs (motors, battery) are held as logged: that is what was applied.

:func:`reference_states` gives the paper's baseline states from Vicon position alone: the
position itself, and velocity and acceleration from a Savitzky-Golay filter; :func:`references`
the same at several windows and a central-difference velocity (``recordings/references.py``).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from ..data import Run
from ..errors import DataError, SettingsError
from .checks import content_key, longest_run
from .flight_checks import ACCEL_FAULT_MPS2, accelerometer_faults, dropout_mask, input_faults
from .references import CD_HALF_WINDOW_S as CD_HALF_WINDOW_S
from .references import REFERENCE_WINDOWS_S as REFERENCE_WINDOWS_S
from .references import REFERENCES as REFERENCES
from .references import SAVGOL_ORDER as SAVGOL_ORDER
from .references import SAVGOL_WINDOW as SAVGOL_WINDOW
from .references import central_velocity as central_velocity
from .references import reference_states as reference_states
from .references import references as references

GRAVITY = 9.81  # [m/s^2], the constant the README's conversion uses
PWM_FULL = 65535.0
POSITION = ("px", "py", "pz")
QUATERNION = ("qx", "qy", "qz", "qw")
ACCEL = ("imu_acc_x", "imu_acc_y", "imu_acc_z")
MOTORS = tuple(f"motor_motor_m{i}" for i in range(1, 5))
VBAT = "pwr_pm_vbat"
COMMAND = "pid_controller_cmd_thrust"  # checked for its range when present
ONBOARD = tuple(f"est_stateEstimate_{n}" for n in ("x", "y", "z", "vx", "vy", "vz", "ax", "ay", "az"))
REQUIRED = ("t", *POSITION, *QUATERNION, *ACCEL, *MOTORS, VBAT, *ONBOARD)
#: Measured channel groups whose exact repeat marks a held (not re-sampled) value.
MEASURED = {"position": POSITION, "acceleration": ACCEL}
HELD = ("missing", "hold")

#: A flight shorter than this after its faulty spans are cut is left out [s].
MIN_FLIGHT_S = 3.0


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
    reference : (T, 9) Savitzky-Golay reference states ``[p, v, a]`` (:func:`reference_states`,
        the paper's window).
    onboard : (T, 9) the Crazyflie EKF's ``[p, v, a]`` (world frame).
    quaternion : (T, 4) Vicon attitude ``(qx, qy, qz, qw)``.
    vbat : (T,) battery voltage [V].
    timing : the time stamps' regularity (:class:`Timing`).
    trimmed : ``(first, last)`` sample indices of the flight in the resampled log.
    truncated : whether a check cut the flight short (``findings`` say where and why).
    metadata : the ``_metadata.yaml`` beside the CSV as flat ``key: value`` strings (``{}``
        when absent).
    references : reference name (:data:`REFERENCES`) -> (T, 9) ``[p, v, a]``, NaN where a
        reference has no value for a state (``cd_0.1s`` has no acceleration).
    findings : what the checks found (:class:`~.checks.Finding`), in the log's seconds.
    key : :func:`~.checks.content_key` of the log's required columns: two files with the same
        key hold the same flight.
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
    references: dict = field(default_factory=dict)
    findings: tuple = ()
    key: str = ""

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


def read_table(path: str | Path, dropped: list | None = None) -> dict[str, np.ndarray]:
    """Read a flight CSV into ``column -> (N,) array``, checking columns and values.

    A row with a non-finite value in a required column (a marker occlusion, a lost packet)
    raises :class:`DataError`, unless ``dropped`` is a list: then the row is left out (the
    resampling bridges it, or the reader cuts the flight at the gap) and its data-row number
    appended to ``dropped``.
    """
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
    bad = np.zeros(table.shape[0], bool)
    for name in REQUIRED:
        rows = ~np.isfinite(columns[name])
        if rows.any() and dropped is None:
            first = int(np.argmax(rows))
            raise DataError(f"{path}: non-finite value in column {name!r} at data row {first + 1} "
                            f"({int(rows.sum())} in that column)")
        bad |= rows
    if bad.any():
        dropped.extend(int(r) + 1 for r in np.flatnonzero(bad))
        columns = {name: values[~bad] for name, values in columns.items()}
        if len(columns["t"]) < 2:
            raise DataError(f"{path}: fewer than 2 rows with finite values in every required column")
    return columns


def check_timing(t: np.ndarray, where: str, max_gap_s: float | None = None) -> Timing:
    """Check that ``t`` increases strictly (and, with ``max_gap_s``, has no gap longer than
    that; :func:`read_flight` instead cuts the flight at such a gap)."""
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise DataError(f"{where}: time must increase strictly; t[{k + 1}]={t[k + 1]!r} after "
                        f"t[{k}]={t[k]!r}")
    # The median interval, to the microsecond: absolute host times of ~1.7e9 s stored as
    # doubles carry ~1e-7 s of round-off, which must not make 0.01 s into 0.0099999905 s.
    dt = round(float(np.median(steps)), 6)
    longest = float(steps.max())
    if max_gap_s is not None and longest > max_gap_s:
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


def airborne_span(height: np.ndarray, pwm: np.ndarray, trim_height_m: float,
                  faulty: np.ndarray | None = None) -> tuple[int, int]:
    """``(first, last)``: the longest stretch in which the motors run and the height is above
    the ground level (before the motors start) plus ``trim_height_m``, and (with ``faulty``)
    no sample is faulty."""
    start = int(np.argmax(pwm > 0))  # first sample with the motors running
    ground = float(np.median(height[:start])) if start > 0 else float(height[0])
    flying = (pwm > 0) & (height > ground + trim_height_m)
    if not flying.any() or longest_run(flying)[1] - longest_run(flying)[0] < 1:
        raise DataError(f"no airborne samples: the vehicle never rises {trim_height_m} m above the "
                        f"ground level {ground:.3f} m with the motors running")
    # a touch-and-go at the end is not part of the flight: the longest stretch is
    span = longest_run(flying & ~faulty) if faulty is not None else longest_run(flying)
    if span is None or span[1] - span[0] < 1:
        raise DataError("no airborne samples free of faults (see the findings above)")
    return span


def read_flight(path: str | Path, *, trim: bool = True, trim_height_m: float = 0.15,
                max_gap_s: float = 0.05, accel_fault_mps2: float = ACCEL_FAULT_MPS2,
                savgol_window: int = SAVGOL_WINDOW, savgol_order: int = SAVGOL_ORDER,
                held: str = "missing", min_flight_s: float = MIN_FLIGHT_S) -> Flight:
    """Read a NanoBench flight CSV into a trimmed, uniformly sampled :class:`Flight`.

    Parameters
    ----------
    path : the flight's CSV.
    trim : cut take-off and landing (see the module docstring).
    trim_height_m : height above the ground level that counts as airborne [m]. 0.15 m cuts
        the touchdown: at 0.05 m, four of the 17 NanoBench flights end with a 30-60 m/s^2
        landing impact.
    max_gap_s : the longest sample interval that is bridged by resampling [s]; a longer gap
        (or rows with non-finite values) is a dropout, and the flight is cut there.
    accel_fault_mps2 : how far the accelerometer may leave the motion capture's acceleration
        (0.5 s mean, beyond its flight's offset) before the span is a fault
        (:func:`~.flight_checks.accelerometer_faults`; ``B2_circle_medium_rep3``: the battery
        browns out near the end of the log and the accelerometer reads > 100 m/s^2).
    savgol_window, savgol_order : the paper's reference filter (``reference``); the
        ``references`` are :func:`references`. Both run on the whole log before trimming.
    held : ``"missing"``: a held position or accelerometer value is a missing output (NaN);
        ``"hold"``: it is used as a sample (see the module docstring, step 4).
    min_flight_s : a flight shorter than this once its faulty spans are cut is left out
        (:class:`DataError` naming the findings).

    Raises
    ------
    DataError : missing columns, non-numeric values, time not increasing, a bad quaternion,
        no airborne part, too little left after cutting faulty spans.
    """
    if held not in HELD:
        raise SettingsError(f"read_flight: held must be one of {HELD}, got {held!r}")
    path = Path(path)
    dropped: list[int] = []
    columns = read_table(path, dropped)
    key = content_key([columns[n] for n in REQUIRED])
    t = columns.pop("t")
    timing = check_timing(t, str(path))
    rows_t = t - t[0]
    t, c = _resample(t, columns, timing.dt, held_rows(columns) if held == "missing" else None)
    quat = c["quaternion"]
    pwm = np.mean([c[m] for m in MOTORS], axis=0) / PWM_FULL
    position = np.stack([c[n] for n in POSITION], axis=1)
    acc = world_acceleration(quat, np.stack([c[n] for n in ACCEL], axis=1))
    faulty, findings = dropout_mask(path.stem, rows_t, t, max_gap_s, max(REFERENCE_WINDOWS_S) / 2,
                                    len(dropped))
    bad_inputs, found = input_faults(path.stem, rows_t, columns, t, (*MOTORS, COMMAND))
    faulty, findings = faulty | bad_inputs, findings + found
    try:
        if trim:
            first, last = airborne_span(position[:, 2], np.clip(pwm, 0, None), trim_height_m)
            bad_accel, found = accelerometer_faults(path.stem, acc, position, timing.dt, (first, last),
                                                    accel_fault_mps2)
            faulty, findings = faulty | bad_accel, findings + found
            first, last = airborne_span(position[:, 2], np.clip(pwm, 0, None), trim_height_m, faulty)
        else:
            first, last = longest_run(~faulty) if faulty.any() else (0, len(t) - 1)
        reference = reference_states(position, timing.dt, savgol_window, savgol_order)
    except DataError as exc:
        raise DataError(f"{path}: {exc}" + "".join(f"; {f.line()}" for f in findings)) from exc
    kept = f"kept {t[first]:.2f}-{t[last]:.2f} s of the log"
    findings = [replace(f, note=f"{f.note}; {kept}" if f.note else kept) for f in findings]
    if t[last] - t[first] < min_flight_s:
        raise DataError(f"{path}: {t[last] - t[first]:.1f} s left once the faulty spans are cut, "
                        f"less than {min_flight_s:g} s: " + "; ".join(f.line() for f in findings))
    u = np.hstack([thrust_vector(quat, pwm), c[VBAT][:, None]])
    y = np.hstack([position, acc])
    for group, block in (("position", slice(0, 3)), ("acceleration", slice(3, 6))):
        if f"missing_{group}" in c:
            y[c[f"missing_{group}"], block] = np.nan
    sl = slice(first, last + 1)
    run = Run(t[sl] - t[first], u[sl], y[sl], None, "quadrotor")
    onboard = np.stack([c[n] for n in ONBOARD], axis=1)
    truncated = bool(findings)
    return Flight(path.stem, run, reference[sl], onboard[sl], quat[sl], c[VBAT][sl], timing,
                  (first, last), truncated, read_metadata(path),
                  {k: v[sl] for k, v in references(position, timing.dt).items()}, tuple(findings), key)
