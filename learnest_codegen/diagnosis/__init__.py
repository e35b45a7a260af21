"""``learnest diagnose``: where a prior's sim-to-real gap lies, which effect causes it, how far it shrinks.

The public API; the modules follow the data: ``loading`` (runs and recordings) -> ``segments``
(state observations, missing samples, held-out split) -> ``floor`` (the noise floor) -> ``where``
-> ``effects``, ``generic_effects``, ``actuator_effects`` and ``system_effects`` (the candidate
library) -> ``fit`` (one-step residual, features) -> ``cv`` (bounded, cross-validated least
squares) -> ``search``, ``selection`` and ``refine`` (the selection's moves and tests, damped
bounded refit) -> ``pooling`` (runs held out in turn, consistency) -> ``shrink`` (held-out
evidence, verdicts) -> ``findings`` / ``report`` (JSON, Markdown, figures); ``selftest`` (with
``selftest_cases`` and ``selftest_systems``) checks all of it on withheld effects.
"""

from . import actuator_effects as actuator_effects  # registers the actuator dynamics kinds
from . import generic_effects as generic_effects  # registers the generic effect kinds
from . import system_effects as system_effects  # registers the built-in systems' own effects
from .core import Diagnosis as Diagnosis
from .core import diagnose as diagnose
from .effects import Effect as Effect
from .effects import corrected_dynamics as corrected_dynamics
from .effects import corrected_system as corrected_system
from .effects import describe_library as describe_library
from .effects import filter_inputs as filter_inputs
from .effects import library as library
from .findings import summary as summary
from .fit import FitSettings as FitSettings
from .fit import Pairs as Pairs
from .loading import FORMATS as FORMATS
from .loading import Recordings as Recordings
from .loading import load as load
from .loading import load_recordings as load_recordings
from .loading import load_runs as load_runs
from .settings import DiagnosisSettings as DiagnosisSettings

__all__ = ["Diagnosis", "DiagnosisSettings", "Effect", "FORMATS", "FitSettings", "Pairs", "Recordings",
           "corrected_dynamics", "corrected_system", "describe_library", "diagnose", "filter_inputs",
           "library", "load", "load_recordings", "load_runs", "summary"]
