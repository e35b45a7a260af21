"""Instructions per sample of the generated C estimators, counted by callgrind (load-independent).

For each estimator (the UKF, ``mhe_rti`` and ``mhe_gn``, N = 20 unless ``--horizon``) of the
KNODE cartpole (or ``--system``; float64 unless ``--precision``), with the default residual net
at its seed-0 initialisation (the same C as a trained one), a plain C main is built from the
generated folder's sources with the documented flags (``-O2 -std=c99 -fno-math-errno``),
stepped over T1 and T2 samples of a simulated run (seed 1) under ``valgrind --tool=callgrind``;
instructions per sample = (I(T2) - I(T1)) / (T2 - T1), so start-up and init cancel. Usage::

    python scripts/bench_callgrind.py --out bench_callgrind.json [--estimators ukf mhe_rti]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import tempfile
from pathlib import Path

import numpy as np
import torch

from learnest_codegen import get_system
from learnest_codegen.compilation import MHE_NAMES, compile_estimators, estimator_dir
from learnest_codegen.export import hybrid_model
from learnest_codegen.learning.training import make_net
from learnest_codegen.simulation import simulate

MAIN = r"""
#include <stdio.h>
#include <stdlib.h>
#include "@HEADER@"
typedef @PREFIX@_real real;
static const double U[@T@][@NU@] = @U@, Y[@T@][@NY@] = @Y@;
int main(void) {
  static unsigned char mem[@WS@];
  real u[@NU@], y[@NY@], x[@NX@];
  @PREFIX@_t* h;
  int k, i;
  double sum = 0;
  if (@INIT@ != 0) return 1;
  for (k = 0; k < @T@; ++k) {
    for (i = 0; i < @NU@; ++i) u[i] = (real)(k ? U[k - 1][i] : 0.0);
    for (i = 0; i < @NY@; ++i) y[i] = (real)Y[k][i];
    if (@STEP@ < 0) return 2;
    @PREFIX@_get_state(h, x);
    for (i = 0; i < @NX@; ++i) sum += x[i];
  }
  printf("%.17g\n", sum);
  return 0;
}
"""


def c_array(values) -> str:
    values = np.atleast_2d(values)
    return "{" + ",".join("{" + ",".join(repr(float(v)) for v in row) + "}" for row in values) + "}"


def api_calls(directory: Path, prefix: str) -> tuple[str, str, str]:
    """(header, init, step) of the folder's C API: init from its tuned defaults."""
    header = f"{prefix}.h"
    text = (directory / header).read_text()
    step = (f"{prefix}_step(h, u, y, 0)" if re.search(rf"int {prefix}_step\([^)]*valid", text)
            else f"{prefix}_step(h, u, y)")
    return header, f"{prefix}_init_default(mem, sizeof mem, &h)", step


def instructions(exe: Path) -> int:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "callgrind.out"
        subprocess.run(["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", str(exe)],
                       check=True, capture_output=True)
        summary = re.search(r"^summary: (\d+)", out.read_text(), re.M)
        return int(summary.group(1))


def build(directory: Path, prefix: str, run, T: int, work: Path) -> Path:
    header, init, step = api_calls(directory, prefix)
    size = int(re.search(rf"#define {prefix.upper()}_WORKSPACE_BYTES \(?(\d+)",
                         (directory / header).read_text()).group(1))
    source = MAIN
    for key, value in {"HEADER": header, "PREFIX": prefix, "T": str(T), "NU": str(run.u.shape[1]),
                       "NY": str(run.y.shape[1]), "NX": str(run.x.shape[1]), "WS": str(size),
                       "U": c_array(run.u[:T]), "Y": c_array(run.y[:T]), "INIT": init,
                       "STEP": step}.items():
        source = source.replace(f"@{key}@", value)
    main_c = work / f"main_{prefix}_{T}.c"
    main_c.write_text(source)
    exe = main_c.with_suffix("")
    sources = [p for p in sorted(directory.glob("*.c"))]
    subprocess.run(["gcc", "-O2", "-std=c99", "-fno-math-errno", str(main_c), *map(str, sources),
                    f"-I{directory}", "-lm", "-o", str(exe)], check=True)
    return exe


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench_callgrind.json"))
    parser.add_argument("--estimators", nargs="+", default=["ukf", "mhe_rti", "mhe_gn"])
    parser.add_argument("--system", default="cartpole", help="built-in system (default cartpole)")
    parser.add_argument("--precision", choices=("float64", "float32"), default="float64")
    parser.add_argument("--horizon", type=int, default=20)
    parser.add_argument("--samples", type=int, nargs=2, default=[100, 300], metavar=("T1", "T2"))
    parser.add_argument("--build-dir", type=Path, default=None)
    args = parser.parse_args(argv)
    system = get_system(args.system)
    torch.manual_seed(0)
    model = hybrid_model(system, make_net(system))
    run = simulate(system, seed=1, duration=max(args.samples) * system.dt)
    report = {"system": system.name, "model": "knode (untrained, seed 0)", "horizon": args.horizon,
              "precision": args.precision,
              "samples": args.samples, "flags": "-O2 -std=c99 -fno-math-errno", "results": {}}
    with tempfile.TemporaryDirectory() as tmp:
        root = args.build_dir or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        for name in args.estimators:
            compile_estimators(model, root, model_hash="bench", estimators=(name,),
                               precision=args.precision,
                               horizon=args.horizon if name in MHE_NAMES else None)
            directory = estimator_dir(root, model, name, args.precision, args.horizon)
            prefix = json.loads((directory / "manifest.json").read_text())["prefix"]
            t1, t2 = args.samples
            counts = [instructions(build(directory, prefix, run, T, root)) for T in (t1, t2)]
            report["results"][name] = {"instructions_per_sample": (counts[1] - counts[0]) / (t2 - t1),
                                       "instructions": dict(zip(map(str, (t1, t2)), counts))}
            print(name, report["results"][name])
    args.out.write_text(json.dumps(report, indent=2))
    return report


if __name__ == "__main__":
    main()
