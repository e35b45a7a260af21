"""The quadrotor study's protocols: which flights train a model and which test it.

Each protocol of :data:`PROTOCOLS` is a list of :class:`Fold` (training flights, test flights):

* ``single``: each named flight against every other flight (the paper's protocol), one
  model per named flight;
* ``train-test``: one model trained on all the named flights, tested on every other flight
  (``learnest reproduce quadrotor --train DIR1 --test DIR2``);
* ``leave-type-out``: the flights of one trajectory type against the model trained on all
  flights of the other types (circles -> figure-eights and the reverse);
* ``leave-one-out``: every flight against the model trained on all the others.

:func:`pooled` joins a protocol's folds into one study, each test flight once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

from ..errors import DataError, UnknownNameError
from .quadrotor_cases import Case
from .quadrotor_report import trajectory_type


@dataclass(frozen=True)
class Fold:
    """One training set and the flights it is tested on."""

    label: str
    train: tuple[Case, ...]
    tests: tuple[Case, ...]


def _single(cases: Sequence[Case], train: Sequence[str]) -> list[Fold]:
    return [Fold(name, tuple(c for c in cases if c.name == name), tuple(c for c in cases if c.name != name))
            for name in train]


def _train_test(cases: Sequence[Case], train: Sequence[str]) -> list[Fold]:
    if not train:
        raise DataError("train-test needs the training flights (--train)")
    tests = tuple(c for c in cases if c.name not in train)
    if not tests:
        raise DataError("train-test: every flight is a training flight; name test flights (--test)")
    return [Fold("train_set", tuple(c for c in cases if c.name in train), tests)]


def _leave_type_out(cases: Sequence[Case], train: Sequence[str]) -> list[Fold]:
    types = sorted({trajectory_type(c.name) for c in cases})
    if len(types) < 2:
        raise DataError(f"leave-type-out needs flights of two trajectory types or more, got {types}")
    return [Fold(f"all_but_{t}", tuple(c for c in cases if trajectory_type(c.name) != t),
                 tuple(c for c in cases if trajectory_type(c.name) == t)) for t in types]


def _leave_one_out(cases: Sequence[Case], train: Sequence[str]) -> list[Fold]:
    return [Fold(f"all_but_{c.name}", tuple(o for o in cases if o is not c), (c,)) for c in cases]


PROTOCOLS: dict[str, Callable[[Sequence[Case], Sequence[str]], list[Fold]]] = {
    "single": _single, "train-test": _train_test, "leave-type-out": _leave_type_out,
    "leave-one-out": _leave_one_out}


def folds(cases: Sequence[Case], protocol: str, train: Sequence[str] = ()) -> list[Fold]:
    """The folds of a protocol of :data:`PROTOCOLS` (``train`` names the flights of ``single``
    and ``train-test``)."""
    if protocol not in PROTOCOLS:
        raise UnknownNameError(f"unknown protocol {protocol!r}; choose from {list(PROTOCOLS)}")
    names = [c.name for c in cases]
    unknown = [t for t in train if t not in names]
    if unknown:
        raise UnknownNameError(f"unknown training case(s) {unknown}; choose from {names}")
    return PROTOCOLS[protocol](cases, train)


def pooled(results: Sequence[dict], name: str) -> dict:
    """The folds' results as one study named ``name`` (each test flight once)."""
    cases, trained_on, tunings, training = {}, {}, {}, {}
    for r in results:
        if r.get("tuning"):
            tunings[r["train"]] = r["tuning"]
        training[r["train"]] = r.get("training", {})
        for case, methods_ in r["cases"].items():
            if case in cases:
                raise DataError(f"{name}: test flight {case} appears in two folds")
            cases[case] = methods_
            trained_on[case] = r["train_cases"]
    return {"train": name, "features": results[0]["features"], "cases": cases, "trained_on": trained_on,
            "tunings": tunings, "trainings": training}
