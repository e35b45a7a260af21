"""DART RC-car recordings (JetRacer, Vicon ~100 Hz; IMU, encoder and commands ~10 Hz) as a :class:`Run`.

A DART CSV has one row per Vicon sample with the columns ``vicon time`` [s, host clock],
``vicon x``, ``vicon y`` [m], ``vicon yaw`` [rad, wrapped to (-pi, pi]], the commands
``throttle`` [0..1] and ``steering`` [-1..1], ``vel encoder`` [m/s] and ``safety_value``; the
commands, encoder and IMU hold their last ~10 Hz update between rows. ``elapsed time sensors``
is not a usable clock (zero for the first rows, then jumps of up to 970 s), so the Vicon clock
is the time base.

What :func:`read_recording` does, in order:

1. **Validate**: required columns present, every value numeric and finite, Vicon time strictly
   increasing (exact duplicate rows are dropped first), no gap longer than ``max_gap_s``.
2. **Safety**: throttle is zeroed where ``safety_value == 0`` (the car ignores it then; DART's
   own pre-processing does the same).
3. **Trim** the stationary start and end: keep from ``trim_margin_s`` before the first sample
   that moves (Vicon speed over ``moving_speed`` m/s) or has throttle, to ``trim_margin_s``
   after the last one.
4. **Resample** onto a uniform grid ``t_k = k dt`` (``dt = 0.01 s``, the system's) on the Vicon
   clock: positions and the unwrapped yaw by linear interpolation (the Vicon jitter is
   0.26-0.29 ms rms, steps 8.0-11.8 ms, so interpolation moves a sample by at most ~0.2 mm at
   4 m/s); the commands by zero-order hold, i.e. the value of the last row at or before the
   grid time (the car holds a command until the next one: that is what was applied).
   The encoder is a measurement: a grid sample gets its value only when a new sensor packet
   arrived since the previous grid time, and is missing (NaN) otherwise (``held="missing"``,
   the default); a packet is new when ``elapsed time sensors`` or any sensor channel changed
   from the row before. The car's ~10 Hz packets then give one encoder sample in about ten,
   instead of ten copies of it. ``held="hold"`` keeps the copies (every grid sample then carries the
   last packet's value).
5. **Align the commands**: ``u(t_k)`` is the command held at ``t_k - command_delay_s``. The
   default 0.06 s is the lag at which the steering command best predicts the Vicon path
   curvature in the four recordings (0.05-0.08 s): transport delay and the servo's response
   together. The project's models are Markov in ``(x, u)`` and cannot represent a lag; set
   ``command_delay_s=0`` for the raw row-wise alignment.

The result has ``u = [throttle, steering]``, ``y = [x, y, psi, v_enc]`` (the ``rc_car``
system's outputs) and ``x = None``: real data has no truth.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import Run
from ..errors import DataError, SettingsError
from ..systems.rc_car import RC_CAR
from . import data_root

TIME, X, Y, YAW = "vicon time", "vicon x", "vicon y", "vicon yaw"
THROTTLE, STEERING, ENCODER, SAFETY = "throttle", "steering", "vel encoder", "safety_value"
REQUIRED = (TIME, X, Y, YAW, THROTTLE, STEERING, ENCODER)
#: Columns that change when a new sensor packet (IMU and encoder, ~10 Hz) arrives.
SENSOR_PACKET = ("elapsed time sensors", "acc x (IMU)", "acc y (IMU)", "W (IMU)", ENCODER)
HELD = ("missing", "hold")
BEACONS = ((-5.0, -5.0), (5.0, -5.0), (5.0, 5.0), (-5.0, 5.0))  # around the ~7 m x 6 m arena [m]


@dataclass(frozen=True)
class DartSettings:
    """How a DART recording becomes a uniform run.

    Attributes
    ----------
    dt : grid step [s].
    command_delay_s : commands are taken this long before each grid time [s].
    trim_margin_s : stationary time kept before the first and after the last motion [s].
    moving_speed : Vicon speed above which the car counts as moving [m/s].
    max_gap_s : the longest Vicon gap accepted [s].
    held : ``"missing"``: a grid sample without a new encoder packet is missing (NaN);
        ``"hold"``: it repeats the last packet's value (see the module docstring, step 4).
    """

    dt: float = RC_CAR.dt
    command_delay_s: float = 0.06
    trim_margin_s: float = 0.5
    moving_speed: float = 0.05
    max_gap_s: float = 0.05
    held: str = "missing"

    def __post_init__(self) -> None:
        if self.held not in HELD:
            raise SettingsError(f"DartSettings.held must be one of {HELD}, got {self.held!r}")
        if not self.dt > 0 or not self.max_gap_s > self.dt:
            raise SettingsError(f"DartSettings: need 0 < dt < max_gap_s, got dt={self.dt}, "
                                f"max_gap_s={self.max_gap_s}")
        for name in ("command_delay_s", "trim_margin_s", "moving_speed"):
            if getattr(self, name) < 0:
                raise SettingsError(f"DartSettings.{name} must be >= 0, got {getattr(self, name)}")


def list_recordings(root: str | Path | None = None) -> list[Path]:
    """The DART CSVs, sorted by name; ``[]`` when there is no data.

    ``root`` may be the data root (holding ``dart/``) or the ``dart`` folder itself; by default
    :func:`~learnest_codegen.recordings.data_root`.
    """
    root = data_root(root)
    if root is None:
        return []
    folder = root / "dart" if (root / "dart").is_dir() else root
    return sorted(folder.glob("*.csv"))


def read_table(path: str | Path) -> dict[str, np.ndarray]:
    """The raw columns of a DART CSV, validated (see the module docstring, step 1)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"DART recording {path} not found")
    with path.open(newline="") as fh:
        header = [h.strip() for h in next(csv.reader(fh), [])]
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise DataError(f"{path}: missing columns {missing}; a DART recording needs {list(REQUIRED)}"
                        f" (has {header})")
    wanted = list(dict.fromkeys(c for c in (*REQUIRED, SAFETY, *SENSOR_PACKET) if c in header))
    try:
        table = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2,
                           usecols=[header.index(c) for c in wanted])
    except ValueError as exc:
        raise DataError(f"{path}: non-numeric content in columns {wanted}: {exc}") from exc
    if table.shape[0] < 2:
        raise DataError(f"{path}: need at least 2 rows, got {table.shape[0]}")
    bad = np.argwhere(~np.isfinite(table))
    if bad.size:
        r, c = bad[0]
        raise DataError(f"{path}: non-finite value in column {wanted[c]!r} at data row {r + 1} "
                        f"({len(bad)} non-finite values in all)")
    keep = np.r_[True, np.any(np.diff(table, axis=0) != 0, axis=1)]  # drop repeated rows
    columns = dict(zip(wanted, table[keep].T))
    t = columns[TIME]
    steps = np.diff(t)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise DataError(f"{path}: '{TIME}' must increase strictly; row {k + 2} has {t[k + 1]!r} "
                        f"after {t[k]!r}")
    return columns


def read_recording(path: str | Path, settings: DartSettings = DartSettings()) -> Run:
    """Read a DART CSV into a uniform ``rc_car`` :class:`Run` (see the module docstring).

    Returns
    -------
    Run with ``t`` (T,) [s] on the file's Vicon clock, counted from its first sample (so the
    trimmed start stays visible), ``u`` (T, 2) ``[throttle, steering]``, ``y`` (T, 4)
    ``[x, y, psi, v_enc]`` and ``x = None``.
    """
    cols = read_table(path)
    t_raw = cols[TIME] - cols[TIME][0]
    gaps = np.diff(t_raw)
    if gaps.max() > settings.max_gap_s:
        k = int(np.argmax(gaps))
        raise DataError(f"{path}: Vicon gap of {gaps[k]:.3f} s at t = {t_raw[k]:.3f} s, more than "
                        f"max_gap_s = {settings.max_gap_s} s")
    throttle = cols[THROTTLE] * (cols[SAFETY] != 0) if SAFETY in cols else cols[THROTTLE]
    yaw = np.unwrap(cols[YAW])
    start, stop = _motion_span(t_raw, cols[X], cols[Y], throttle, settings)
    t = np.arange(start, stop, settings.dt)
    if len(t) < 2:
        raise DataError(f"{path}: the car never moves (speed under {settings.moving_speed} m/s "
                        "and zero throttle throughout)")
    encoder = _hold(t_raw, cols[ENCODER], t)
    if settings.held == "missing":
        encoder = np.where(_fresh(t_raw, cols, t, settings.dt), encoder, np.nan)
    y = np.stack([np.interp(t, t_raw, cols[X]), np.interp(t, t_raw, cols[Y]),
                  np.interp(t, t_raw, yaw), encoder], axis=1)
    t_cmd = t - settings.command_delay_s
    u = np.stack([_hold(t_raw, throttle, t_cmd), _hold(t_raw, cols[STEERING], t_cmd)], axis=1)
    return Run(t, u, y, None, RC_CAR.name)


def _hold(t_raw: np.ndarray, values: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Zero-order hold: the value of the last row at or before each ``t`` (the first before)."""
    return values[np.clip(np.searchsorted(t_raw, t, side="right") - 1, 0, None)]


def _fresh(t_raw: np.ndarray, cols: dict[str, np.ndarray], t: np.ndarray, dt: float) -> np.ndarray:
    """(len(t),) bool: a new sensor packet arrived in ``(t_k - dt, t_k]`` (the first row counts
    as one)."""
    packet = np.column_stack([cols[c] for c in SENSOR_PACKET if c in cols])
    new = np.flatnonzero(np.r_[True, np.any(np.diff(packet, axis=0) != 0, axis=1)])
    last = np.searchsorted(t_raw[new], t, side="right") - 1  # the latest packet at or before t_k
    return (last >= 0) & (t_raw[new][np.clip(last, 0, None)] > t - dt)


def _motion_span(t, x, y, throttle, settings: DartSettings) -> tuple[float, float]:
    """First and last time [s] to keep: the motion (or throttle) plus the margins."""
    speed = np.hypot(np.gradient(x, t), np.gradient(y, t))
    speed = np.convolve(speed, np.ones(5) / 5, mode="same")  # 50 ms: ignore single-sample jitter
    active = np.flatnonzero((speed > settings.moving_speed) | (throttle > 0))
    if active.size == 0:
        return float(t[0]), float(t[0])
    start = max(t[active[0]] - settings.trim_margin_s, t[0])
    stop = min(t[active[-1]] + settings.trim_margin_s, t[-1])
    return float(start), float(stop)


def beacon_ranges(positions: np.ndarray, beacons=BEACONS) -> np.ndarray:
    """Noise-free ranges [m] from planar positions ``(T, 2)`` to beacons ``((bx, by), ...)``.

    Reproduces the paper's range-beacon localisation on real vehicle motion (add noise to
    taste, e.g. the ground robot's 0.05 m). Returns ``(T, n_beacons)``.
    """
    positions = np.asarray(positions, dtype=float)
    if positions.ndim != 2 or positions.shape[1] != 2:
        raise DataError(f"beacon_ranges: positions must have shape (T, 2), got {positions.shape}")
    b = np.asarray(beacons, dtype=float)
    return np.hypot(positions[:, None, 0] - b[None, :, 0], positions[:, None, 1] - b[None, :, 1])
