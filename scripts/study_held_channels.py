"""Held sensor channels taken as fresh samples or as missing: the DART car and the Crazyflie.

DART: the encoder (``v_enc``) arrives in ~10 Hz sensor packets inside the ~100 Hz Vicon rows,
and the recordings repeat it in between. Each of the four recordings is read twice, with the
repeats as samples (``held="hold"``, the reader before missing outputs) and as missing outputs
(``held="missing"``), and estimated by the Python UKF and MHE of the ``rc_car`` prior. There is
no truth; the speed is scored against the speed of the Vicon path (Savitzky-Golay derivative,
0.31 s cubic, as ``tests/test_rc_car.py``) while the car moves faster than 0.3 m/s, and the
pose against the Vicon pose. Crazyflie: every NanoBench flight is read both ways and compared.

    python scripts/study_held_channels.py --out study_held_channels.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.signal import savgol_filter

import learnest_codegen as ln
from learnest_codegen.recordings import crazyflie, dart


def vicon_speed(run) -> np.ndarray:
    """(T,) speed of the Vicon path [m/s]."""
    d = [savgol_filter(run.y[:, i], 31, 3, deriv=1, delta=run.median_dt) for i in (0, 1)]
    return np.hypot(*d)


def initial_state(run) -> np.ndarray:
    """``[x, y, v, psi]`` from the first samples: Vicon pose and the Vicon path's speed."""
    return np.array([run.y[0, 0], run.y[0, 1], vicon_speed(run)[0], run.y[0, 2]])


def dart_rows(paths, estimators) -> list[dict]:
    rows = []
    for path in paths:
        runs = {held: dart.read_recording(path, dart.DartSettings(held=held)) for held in dart.HELD}
        speed = vicon_speed(runs["hold"])
        moving = speed > 0.3
        for held, run in runs.items():
            for name in estimators:
                est = ln.make_estimator("nominal", name, backend="python", system="rc_car")
                start = time.process_time()
                X = est.run(run.u, run.y, initial_state(run))
                seconds = time.process_time() - start
                pose = X[:, [0, 1, 3]] - run.y[:, :3]
                rows.append({
                    "recording": path.stem, "held": held, "estimator": name, "samples": len(run),
                    "encoder_samples": int((~np.isnan(run.y[:, 3])).sum()),
                    "speed_rmse": float(np.sqrt(np.mean((X[moving, 2] - speed[moving]) ** 2))),
                    "speed_bias": float(np.mean(X[moving, 2] - speed[moving])),
                    "pose_rms": np.sqrt(np.mean(pose ** 2, axis=0)).tolist(),
                    "rejected": int(est.rejections), "cpu_seconds": round(seconds, 1)})
                print(json.dumps(rows[-1]), flush=True)
    return rows


def crazyflie_rows(paths) -> list[dict]:
    rows = []
    for path in paths:
        missing, hold = crazyflie.read_flight(path), crazyflie.read_flight(path, held="hold")
        same = all(np.array_equal(a, b, equal_nan=True) for a, b in
                   ((missing.run.y, hold.run.y), (missing.run.u, hold.run.u),
                    (missing.reference, hold.reference)))
        rows.append({"flight": missing.name, "samples": len(missing.run),
                     "missing_outputs": int(np.isnan(missing.run.y).sum()), "identical": same})
    return rows


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=None, help="data root (default: ../shared/data)")
    parser.add_argument("--estimators", nargs="+", default=["ukf", "mhe"])
    parser.add_argument("--out", type=Path, default=Path("study_held_channels.json"))
    args = parser.parse_args(argv)
    from learnest_codegen.recordings import data_root

    root = data_root(args.data)
    if root is None:
        raise SystemExit("no recordings found (../shared/data or $LEARNEST_DATA)")
    result = {"dart": dart_rows(dart.list_recordings(root), args.estimators),
              "crazyflie": crazyflie_rows(crazyflie.list_flights(root))}
    args.out.write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
