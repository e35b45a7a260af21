"""Replay recorded Crazyflie flights through a generated Crazyflie app; build the firmware with
it; time it on a Cortex-M4F under QEMU.

A Crazyflie app is the folder ``learnest-compile MODEL --target crazyflie`` writes
(docs/guide/crazyflie.md). This file, example glue like ``examples/cortex_m``, checks it three
ways:

- **Firmware build.** :func:`unpack_firmware` unpacks the firmware tarball
  (:func:`firmware_tarball`) and makes it the git repository its build wants;
  :func:`build_firmware` runs the firmware's own build, with or without the app, and reads its
  size report.
- **Host replay.** :func:`build_replay` compiles ``src/replay.c``, which includes the app's
  ``estimator_out_of_tree.c``, against the firmware's own headers and the stubs of ``stubs/``;
  :func:`flight_replay` turns a NanoBench flight into the records the firmware would have queued
  (the whole log from the ground up to the end of the airborne part, on the flight's 10 ms grid);
  :func:`run_replay` feeds them and reads, per sample, what the app gave the estimator and what
  it estimated. :func:`bindings_estimates` runs the same samples through the Python bindings.
- **QEMU.** The same replay for QEMU's ``mps2-an386`` (Cortex-M4F), compiled with the flags the
  firmware's build used for the app's files (:func:`firmware_cflags`), the flight in flash; the
  sample clock counts instructions (``-icount shift=0``: 40 a tick, as in examples/cortex_m).

    python examples/crazyflie/replay.py generated/<prefix>_crazyflie --compiled generated/<prefix> \\
        --flight ../shared/data/nanobench/B2_circle_fast_rep1.csv [--qemu] [--build-firmware]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import tarfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from learnest_codegen.errors import BuildError, DataError
from learnest_codegen.recordings import data_root
from learnest_codegen.recordings.crazyflie import check_timing, read_flight, read_table

EXAMPLE_DIR = Path(__file__).resolve().parent
ROOT = EXAMPLE_DIR.parents[1]
CORTEX_M = ROOT / "examples" / "cortex_m"
FIRMWARE_ENV = "LEARNEST_CRAZYFLIE_FIRMWARE"
TOOLS = ("arm-none-eabi-gcc", "make", "gcc", "git")
QEMU = "qemu-system-arm"
QEMU_TIMEOUT_S = 600
#: Firmware headers the app includes (beside the stubs), relative to the firmware's root.
FIRMWARE_INCLUDES = ("src/modules/interface", "src/modules/interface/estimator", "src/hal/interface",
                     "src/utils/interface", "src/utils/interface/lighthouse")
#: The host build of the app: the firmware's language and warnings, no fused multiply-add
#: (the app's Kbuild asks the same of the firmware's build).
HOST_APP_FLAGS = ("-O2", "-std=gnu11", "-ffp-contract=off", "-fno-math-errno", "-fno-strict-aliasing",
                  "-Wall", "-Wdouble-promotion", "-Werror")
FIELDS = 20  # replay_source.h
FIRMWARE_DATE = "2026-08-21T00:00:00Z"  # the firmware commit's date (../shared/vendor/README.md)
SIZE_LINE = re.compile(r"^(Flash|RAM|CCM)\s*\|\s*(\d+)/(\d+)", re.M)
GRID_SLACK = 1e-6  # recordings.crazyflie's grid: floor(t_end / dt + 1e-6) + 1 samples


def firmware_tarball() -> Path | None:
    """The firmware tarball: ``$LEARNEST_CRAZYFLIE_FIRMWARE``, else the newest
    ``crazyflie-firmware-*.tar.xz`` in ``../shared/vendor`` (from the current folder or the
    project's root) or in the ``vendor`` folder beside the recordings' (``$LEARNEST_DATA``);
    ``None`` when there is none."""
    given = os.environ.get(FIRMWARE_ENV)
    if given:
        return Path(given) if Path(given).is_file() else None
    folders = [Path.cwd().parent / "shared" / "vendor", ROOT.parent / "shared" / "vendor"]
    data = data_root()
    if data is not None:
        folders.append(data.parent / "vendor")
    for folder in folders:
        found = sorted(folder.glob("crazyflie-firmware-*.tar.xz"))
        if found:
            return found[-1]
    return None


def missing_tools(qemu: bool = False) -> list[str]:
    """What the builds need and is not there (programs on PATH, the tarball)."""
    missing = [t for t in (*TOOLS, *((QEMU,) if qemu else ())) if shutil.which(t) is None]
    if firmware_tarball() is None:
        missing.append(f"the firmware tarball (${FIRMWARE_ENV} or ../shared/vendor)")
    return missing


def _run(command: list[str], cwd: Path | None = None, **kwargs) -> subprocess.CompletedProcess:
    result = subprocess.run(command, cwd=cwd, capture_output=True, text=True, **kwargs)
    if result.returncode != 0:
        raise BuildError(f"{' '.join(map(str, command))} (in {cwd or Path.cwd()}) failed with "
                         f"exit code {result.returncode}:\n{(result.stdout + result.stderr)[-4000:]}")
    return result


# -- the firmware ----------------------------------------------------------------------------------


def unpack_firmware(dest: Path, tarball: Path | None = None) -> Path:
    """The firmware tree, unpacked into ``dest`` and committed and tagged as a git repository
    (the build stamps its version from git; ../shared/vendor/README.md). Reused when there."""
    tarball = tarball or firmware_tarball()
    if tarball is None:
        raise BuildError(f"no firmware tarball: set ${FIRMWARE_ENV} or put it in ../shared/vendor")
    root = Path(dest) / "crazyflie-firmware"
    if (root / ".git").is_dir() and (root / "tools" / "make" / "oot.mk").is_file():
        return root
    Path(dest).mkdir(parents=True, exist_ok=True)
    with tarfile.open(tarball) as archive:
        archive.extractall(dest, filter="tar")
    git = ["git", "-c", "user.name=replay", "-c", "user.email=replay@localhost", "-c", "core.autocrlf=false"]
    # fixed dates: every unpack gets the same commit, which the build stamps into cf2.bin
    dated = {**os.environ, "GIT_AUTHOR_DATE": FIRMWARE_DATE, "GIT_COMMITTER_DATE": FIRMWARE_DATE}
    _run(["git", "init", "-q"], root)
    _run([*git, "add", "-A"], root)
    _run([*git, "commit", "-qm", "firmware"], root, env=dated)
    _run(["git", "tag", "2026.08"], root)
    return root


@dataclass(frozen=True)
class SizeReport:
    """The firmware build's size report (tools/make/size.py): bytes used and available."""

    flash_used: int
    flash_total: int
    ram_used: int
    ram_total: int
    ccm_used: int
    ccm_total: int

    def to_json(self) -> dict:
        out = {}
        for region in ("flash", "ram", "ccm"):
            used, total = getattr(self, f"{region}_used"), getattr(self, f"{region}_total")
            out[region] = {"used": used, "total": total, "free": total - used}
        return out


def parse_size_report(text: str) -> SizeReport:
    found = {name.lower(): (int(used), int(total)) for name, used, total in SIZE_LINE.findall(text)}
    if set(found) != {"flash", "ram", "ccm"}:
        raise BuildError(f"no size report (Flash, RAM, CCM lines) in the build's output:\n{text[-2000:]}")
    return SizeReport(*found["flash"], *found["ram"], *found["ccm"])


@dataclass(frozen=True)
class FirmwareBuild:
    binary: Path
    sizes: SizeReport
    seconds: float
    warnings: tuple[str, ...]  # compiler warnings about the app's files (the build has -Werror)


def build_firmware(firmware: Path, app: Path | None = None, jobs: int = 2) -> FirmwareBuild:
    """``make cf2_defconfig && make`` of the firmware alone (``app=None``: into the tree's
    ``build/``) or with the app (in the app's folder, ``CRAZYFLIE_BASE`` the firmware: into
    ``<app>/build/``)."""
    start = time.perf_counter()
    where = Path(app) if app is not None else Path(firmware)
    base = [f"CRAZYFLIE_BASE={Path(firmware).resolve()}"] if app is not None else []
    _run(["make", *base, "cf2_defconfig"], where)
    log = _run(["make", *base, f"-j{jobs}"], where)
    text = log.stdout + log.stderr
    binary = where / "build" / "cf2.bin"
    if not binary.is_file():
        raise BuildError(f"the firmware's build finished without {binary}")
    warnings = tuple(line for line in text.splitlines()
                     if "warning:" in line and app is not None and str(Path(app).resolve()) in line)
    return FirmwareBuild(binary, parse_size_report(text), time.perf_counter() - start, warnings)


#: Input sections by where they land (tools/make/F405/linker): flash holds code, constants and
#: the initial values of .data; RAM .data and .bss; CCM .ccmbss.
REGIONS = {".text": ("flash",), ".rodata": ("flash",), ".data": ("flash", "ram"), ".bss": ("ram",),
           "COMMON": ("ram",), ".ccmbss": ("ccm",)}
MAP_SECTION = re.compile(r"^ (?P<name>[.\w]+)(?:\s+0x[0-9a-f]+\s+0x(?P<size>[0-9a-f]+)\s+(?P<file>\S+))?$")
MAP_PLACE = re.compile(r"^\s+0x[0-9a-f]+\s+0x(?P<size>[0-9a-f]+)\s+(?P<file>\S+)$")


def app_memory(build: FirmwareBuild, app: Path) -> dict[str, int]:
    """The bytes of flash, RAM and CCM the app's own objects take in the linked firmware (the
    input sections of its folder's objects in the build's linker map, after the link dropped
    what nothing uses)."""
    text = (build.binary.parent / "cf2.map").read_text()
    text = text.split("Linker script and memory map", 1)[-1]
    folder = str(Path(app).resolve())
    out = {"flash": 0, "ram": 0, "ccm": 0}
    name = None
    for line in text.splitlines():
        m = MAP_SECTION.match(line)
        if m:
            name, size, file = m.group("name"), m.group("size"), m.group("file")
        else:
            placed = MAP_PLACE.match(line) if name else None
            if not placed:
                name = None
                continue
            size, file = placed.group("size"), placed.group("file")
        if size is None or not file.startswith(folder):
            continue
        kind = next((k for k in REGIONS if name == k or name.startswith(k + ".")), None)
        for region in REGIONS.get(kind, ()):
            out[region] += int(size, 16)
        name = None
    return out


def path_occurrences(build: FirmwareBuild, *folders: Path) -> int:
    """How often the absolute paths of ``folders`` occur in ``cf2.bin``: 0 when the build names
    its files independently of where they are checked out (the app's Makefile maps them)."""
    data = build.binary.read_bytes()
    return sum(data.count(str(Path(f).resolve()).encode()) for f in folders)


def firmware_cflags(cmd_file: Path) -> list[str]:
    """The flags the firmware's build compiled one file with (its Kbuild ``.<name>.o.cmd``),
    without the include folders, the dependency output and the file names."""
    line = Path(cmd_file).read_text().splitlines()[0]
    words = line.split(":=", 1)[1].split()
    flags, skip = [], False
    for word in words[1:]:  # words[0]: the compiler
        if skip:
            skip = False
        elif word in ("-o",):
            skip = True
        elif word.startswith(("-I", "-Wp,")) or word == "-c" or not word.startswith("-"):
            continue
        else:
            flags.append(word)
    return flags


# -- flights ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FlightReplay:
    """A flight as the firmware would have queued it, and what to score it against.

    ``records`` (T, 20) float32: one per 10 ms sample from the log's start (on the ground) to the
    last airborne sample; ``u``, ``y`` (T, ...) the recordings pipeline's inputs and
    measurements of the same samples (``y`` NaN where missing); ``span`` the airborne samples
    ``[first, last]``; ``reference`` and ``onboard`` (last - first + 1, 9) their Vicon reference
    states and the onboard EKF's.
    """

    name: str
    records: np.ndarray
    u: np.ndarray
    y: np.ndarray
    span: tuple[int, int]
    reference: np.ndarray
    onboard: np.ndarray


def flight_replay(path: Path) -> FlightReplay:
    """The records of the NanoBench flight ``path`` (see :class:`FlightReplay`).

    The pose, the accelerometer, the gyroscope, the motors and the battery are the log's, on the
    grid of :func:`~learnest_codegen.recordings.crazyflie.read_flight` (the same interpolation;
    the pose's attitude its slerp); the motor ratios rounded to the integers a firmware holds.
    """
    path = Path(path)
    flight = read_flight(path)
    # The firmware sees the whole log from the ground up, so the records come from the untrimmed
    # reading (trim=False applies no accelerometer fault cut: that check runs on the airborne
    # span only). The records end at the trimmed flight's last sample, and the scores cover its
    # airborne span, so a faulty span the reader cuts (B2_circle_medium_rep3's brown-out) is
    # neither fed nor scored; one before the span is fed, as the vehicle lived through it. The
    # untrimmed reading still cuts at a dropout or an input fault (B2_circle_medium_rep3's motor
    # values after 31.3 s): it must keep the log from its start to the flight's end.
    whole = read_flight(path, trim=False)
    first, last = flight.trimmed
    columns = read_table(path)
    t = columns.pop("t")
    dt = check_timing(t, str(path), 0.05).dt
    grid = dt * np.arange(int(np.floor((t[-1] - t[0]) / dt + GRID_SLACK)) + 1)
    if whole.trimmed[0] != 0 or whole.trimmed[1] < last or whole.trimmed[1] >= grid.size:
        raise DataError(f"{path}: the untrimmed log keeps samples {list(whole.trimmed)} of {grid.size}; "
                        f"the replay needs 0 to the flight's end, {last}")

    def column(name: str) -> np.ndarray:
        return np.interp(grid, t - t[0], columns[name])

    T = last + 1
    y = whole.run.y[:T]
    records = np.zeros((T, FIELDS), dtype=np.float64)
    records[:, 0:3] = np.nan_to_num(y[:, 0:3])
    records[:, 3:7] = whole.quaternion[:T]
    records[:, 7] = np.all(np.isfinite(y[:, 0:3]), axis=1)
    records[:, 8:11] = np.column_stack([column(f"imu_acc_{a}") for a in "xyz"])[:T]
    records[:, 11] = np.all(np.isfinite(y[:, 3:6]), axis=1)
    records[:, 12:15] = np.degrees(np.column_stack([column(f"imu_gyro_{a}") for a in "xyz"]))[:T]
    records[:, 15:19] = np.clip(np.rint(np.column_stack([column(f"motor_motor_m{i}") for i in range(1, 5)])),
                                0, 65535)[:T]
    records[:, 19] = whole.vbat[:T]
    return FlightReplay(flight.name, records.astype(np.float32), whole.run.u[:T], y, (first, last),
                        flight.reference, flight.onboard)


# -- the replay's builds ---------------------------------------------------------------------------


def _estimator_folder(app: Path) -> Path:
    folders = [p for p in (Path(app) / "src").iterdir() if p.is_dir() and (p / "Kbuild").is_file()]
    if len(folders) != 1:
        raise BuildError(f"{app}/src should hold one estimator folder, found {[p.name for p in folders]}")
    return folders[0]


def _estimator_flags(folder: Path) -> list[str]:
    """The estimator's flags from its build fragment (``<PREFIX>_CFLAGS``), without ``-I``."""
    text = (folder / f"{folder.name}.mk").read_text()
    match = re.search(rf"^{folder.name.upper()}_CFLAGS := (.*)$", text, re.M)
    if not match:
        raise BuildError(f"{folder.name}.mk defines no {folder.name.upper()}_CFLAGS")
    return [w for w in match.group(1).split() if not w.startswith("-I")]


def _includes(app: Path, firmware: Path) -> list[str]:
    folder = _estimator_folder(app)
    dirs = [EXAMPLE_DIR / "stubs", EXAMPLE_DIR / "src", Path(app) / "src", folder,
            *(Path(firmware) / d for d in FIRMWARE_INCLUDES)]
    return [f"-I{d}" for d in dirs]


def _compile(cc: str, sources: list[tuple[Path, list[str]]], out: Path, link: list[str]) -> Path:
    out.parent.mkdir(parents=True, exist_ok=True)
    objects = []
    for source, flags in sources:
        obj = out.parent / f"{source.stem}.o"
        _run([cc, *flags, "-c", str(source), "-o", str(obj)])
        objects.append(str(obj))
    _run([cc, *objects, *link, "-o", str(out)])
    return out


def build_replay(app: Path, firmware: Path, out: Path) -> Path:
    """The host build of the replay: the app with :data:`HOST_APP_FLAGS`, its estimator with the
    flags of its build fragment (those of the Python bindings' library)."""
    folder = _estimator_folder(app)
    includes = _includes(app, firmware)
    app_flags = [*HOST_APP_FLAGS, *includes]
    est = [*_estimator_flags(folder), f"-I{folder}"]
    sources = [(EXAMPLE_DIR / "src" / "replay.c", app_flags),
               (EXAMPLE_DIR / "src" / "source_stdin.c", app_flags),
               (CORTEX_M / "src" / "platform_host.c", ["-O2", "-Wall", "-Werror"]),
               *((folder / s, est) for s in (f"{folder.name}.c", f"{folder.name}_model.c"))]
    return _compile("gcc", sources, Path(out) / "replay", ["-lm"])


def write_flight_data(path: Path, records: np.ndarray) -> Path:
    """``flight_data.h``: ``REPLAY_RECORDS`` and ``replay_data`` as exact hex-float constants."""
    rows = ",\n".join("{" + ", ".join(float(v).hex() + "f" for v in row) + "}"
                      for row in np.asarray(records, dtype=np.float32))
    path.write_text("/* flight_data.h: a flight's replay records (written by replay.py). */\n"
                    f"#define REPLAY_RECORDS {len(records)}u\n"
                    f"static const float replay_data[{len(records)}][{FIELDS}] = {{\n{rows}\n}};\n")
    return path


def build_qemu(app: Path, firmware: Path, records: np.ndarray, out: Path) -> Path:
    """The replay for QEMU's mps2-an386 with ``records`` in flash, every file of the app compiled
    with the flags the firmware's build used for it (the app must have been built)."""
    folder = _estimator_folder(app)
    app_cmd = Path(app) / "src" / ".estimator_out_of_tree.o.cmd"
    est_cmd = folder / f".{folder.name}.o.cmd"
    if not (app_cmd.is_file() and est_cmd.is_file()):
        raise BuildError(f"{app} has not been built by the firmware yet (no {app_cmd.name}): build it first")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_flight_data(out / "flight_data.h", records)
    includes = [*_includes(app, firmware), f"-I{out}"]
    app_flags = [*firmware_cflags(app_cmd), *includes]
    est_flags = [*firmware_cflags(est_cmd), f"-I{folder}"]
    target = [w for w in app_flags if w.startswith(("-mcpu", "-mthumb", "-mfloat-abi", "-mfpu"))]
    platform = [*target, "-O2", "-std=c99", "-Wall", "-Werror", f"-I{CORTEX_M / 'src'}"]
    sources = [(EXAMPLE_DIR / "src" / "replay.c", app_flags),
               (EXAMPLE_DIR / "src" / "source_flash.c", app_flags),
               (CORTEX_M / "src" / "platform_mps2.c", platform),
               (CORTEX_M / "src" / "startup_mps2.c", platform),
               *((folder / s, est_flags) for s in (f"{folder.name}.c", f"{folder.name}_model.c"))]
    link = [*target, "-nostartfiles", "-T", str(CORTEX_M / "mps2.ld"), "-Wl,--gc-sections",
            "--specs=nano.specs", "--specs=nosys.specs", "-lm"]
    return _compile("arm-none-eabi-gcc", sources, out / "replay.elf", link)


# -- running and reading a replay ------------------------------------------------------------------


@dataclass
class Replay:
    """A replay's output, per sample: whether the estimator had started, the step's status,
    the validity flags, inputs and measurement the app gave it (float32, as given), the estimate
    (NaN before the start), and the sample clock's ticks in the sample's tick and the others."""

    started: np.ndarray
    status: np.ndarray
    valid: np.ndarray
    u: np.ndarray
    y: np.ndarray
    x: np.ndarray
    busy_sample: np.ndarray
    busy_other: np.ndarray
    summary: dict = field(default_factory=dict)


def _floats(words: list[str]) -> np.ndarray:
    return np.array([int(w, 16) for w in words], dtype=np.uint32).view(np.float32)


def parse_replay(text: str, nu: int = 4, ny: int = 6, nx: int = 9) -> Replay:
    rows, summary = [], None
    for line in text.splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "error":
            raise BuildError(f"the replay stopped: {line}")
        if words[0] == "summary":
            summary = {k: int(v) for k, v in (w.split("=") for w in words[1:])}
        elif words[0] == "s":
            rows.append(words)
    if summary is None or summary["samples"] != len(rows):
        raise BuildError(f"the replay's output is cut short ({len(rows)} samples):\n{text[-2000:]}")
    T = len(rows)
    out = Replay(np.zeros(T, bool), np.zeros(T, int), np.zeros((T, ny), bool), np.zeros((T, nu), np.float32),
                 np.zeros((T, ny), np.float32), np.full((T, nx), np.nan, np.float32), np.zeros(T, np.int64),
                 np.zeros(T, np.int64), summary)
    for k, w in enumerate(rows):
        out.started[k], out.status[k] = w[2] == "1", int(w[3])
        out.valid[k] = [c == "1" for c in w[4]]
        out.u[k] = _floats(w[5:5 + nu])
        out.y[k] = _floats(w[5 + nu:5 + nu + ny])
        rest = w[5 + nu + ny:]
        if rest[0] != "-":
            out.x[k] = _floats(rest[:nx])
        out.busy_sample[k], out.busy_other[k] = int(rest[-2]), int(rest[-1])
    return out


def run_replay(binary: Path, records: np.ndarray) -> Replay:
    """Run the host replay over ``records``."""
    result = subprocess.run([str(binary)], input=np.ascontiguousarray(records, np.float32).tobytes(),
                            capture_output=True, timeout=QEMU_TIMEOUT_S)
    if result.returncode != 0:
        raise BuildError(f"{binary} failed ({result.returncode}): {result.stdout[-500:]!r} "
                         f"{result.stderr[-500:]!r}")
    return parse_replay(result.stdout.decode())


def run_qemu(elf: Path) -> Replay:
    """Run the QEMU replay; the sample clock counts instructions (40 a tick)."""
    command = [QEMU, "-M", "mps2-an386", "-nographic", "-monitor", "none", "-serial", "none",
               "-icount", "shift=0,sleep=off", "-semihosting-config", "enable=on,target=native",
               "-kernel", str(elf)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=QEMU_TIMEOUT_S)
    if result.returncode != 0:
        raise BuildError(f"QEMU failed ({result.returncode}): {result.stdout[-1000:]} "
                         f"{result.stderr[-1000:]}")
    return parse_replay(result.stdout)


INSTRUCTIONS_PER_TICK = 40  # examples/cortex_m: a 25 MHz SysTick under -icount shift=0


# -- comparisons -----------------------------------------------------------------------------------


def start_state(replay: Replay) -> tuple[int, np.ndarray]:
    """The first sample the app stepped and the x0 it started from: ``[p, 0, a]`` of that
    sample's measurement (``a`` 0 when it had none)."""
    k0 = int(np.argmax(replay.started))
    if not replay.started[k0]:
        raise DataError("the app never started its estimator (no sample with a position)")
    y, valid = replay.y[k0].astype(np.float64), replay.valid[k0]
    return k0, np.concatenate([y[0:3], np.zeros(3), np.where(valid[3:6], y[3:6], 0.0)])


def bindings_estimates(estimator, replay: Replay) -> np.ndarray:
    """The Python bindings' estimates of the samples the app stepped, given what the app gave its
    estimator (its x0, inputs, measurements and validity flags); NaN before its start."""
    k0, x0 = start_state(replay)
    X = np.full(replay.x.shape, np.nan)
    X[k0:] = estimator.run(replay.u[k0:], replay.y[k0:], x0, valid=replay.valid[k0:])
    return X


def rms_errors(X: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(n_states,) RMS error of ``X`` against ``reference`` (same rows)."""
    return np.sqrt(np.mean((np.asarray(X, float) - reference) ** 2, axis=0))


def main() -> None:
    from learnest_codegen.pipeline import load_estimator

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("app", type=Path, help="the app folder (learnest-compile --target crazyflie)")
    parser.add_argument("--compiled", type=Path, required=True, help="the estimator's folder (bindings)")
    parser.add_argument("--flight", type=Path, action="append", required=True, help="a NanoBench CSV")
    parser.add_argument("--work", type=Path, default=Path("build/crazyflie"), help="scratch folder")
    parser.add_argument("--build-firmware", action="store_true", help="build cf2.bin with the app")
    parser.add_argument("--qemu", action="store_true",
                        help="also replay under QEMU (needs --build-firmware once)")
    args = parser.parse_args()
    firmware = unpack_firmware(args.work)
    report: dict = {}
    if args.build_firmware:
        report["firmware"] = build_firmware(firmware, args.app).sizes.to_json()
    binary = build_replay(args.app, firmware, args.work / "host")
    estimator = load_estimator(args.compiled)
    for path in args.flight:
        flight = flight_replay(path)
        replay = run_replay(binary, flight.records)
        X = bindings_estimates(estimator, replay)
        first, last = flight.span
        entry = {"equal_to_bindings": bool(np.array_equal(np.isnan(X), np.isnan(replay.x))
                                           and np.array_equal(X[~np.isnan(X)], replay.x[~np.isnan(X)])),
                 "rms": rms_errors(replay.x[first:last + 1], flight.reference).tolist(),
                 "onboard_rms": rms_errors(flight.onboard[:, :6], flight.reference[:, :6]).tolist()}
        if args.qemu:
            fw = run_qemu(build_qemu(args.app, firmware, flight.records, args.work / "qemu" / flight.name))
            entry["qemu_equal"] = bool(np.array_equal(fw.x, replay.x, equal_nan=True))
            seconds = len(fw.x) * float(estimator.manifest["dt"])
            entry["instructions_per_second"] = int(
                (fw.busy_sample.sum() + fw.busy_other.sum()) * INSTRUCTIONS_PER_TICK / seconds)
        report[flight.name] = entry
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
