"""learnest_codegen: learned (KNODE) dynamics to compiled C state estimators.

Data flows one way: systems -> simulation/data -> observers -> training -> export ->
codegen -> toolchain -> runtime -> evaluation -> CLI. The names below are the public API; the
pipeline's calls (:mod:`learnest_codegen.pipeline`) import torch only when a trained model is
involved, so ``import learnest_codegen`` stays light.
"""

from .config import DEFAULT_TRAINING as DEFAULT_TRAINING
from .config import NetworkSettings as NetworkSettings
from .config import TrainingSettings as TrainingSettings
from .config import WarmRefinement as WarmRefinement
from .data import Run as Run
from .data import read_run as read_run
from .data import resample as resample
from .data import write_run as write_run
from .errors import BuildError as BuildError
from .errors import DataError as DataError
from .errors import LearnestError as LearnestError
from .errors import ModelMismatchError as ModelMismatchError
from .errors import ObserverError as ObserverError
from .errors import SettingsError as SettingsError
from .errors import ShapeError as ShapeError
from .errors import SolverError as SolverError
from .errors import SystemFileError as SystemFileError
from .errors import UnknownNameError as UnknownNameError
from .estimators.contract import Estimator as Estimator
from .estimators.gate import GateSettings as GateSettings
from .estimators.mhe_gn import GaussNewtonSettings as GaussNewtonSettings
from .estimators.mhe_problem import MHESettings as MHESettings
from .estimators.ukf import UKFSettings as UKFSettings
from .evaluation import mse as mse
from .pipeline import estimator_system as estimator_system
from .pipeline import evaluate as evaluate
from .pipeline import load_estimator as load_estimator
from .pipeline import make_estimator as make_estimator
from .pipeline import resolve as resolve
from .pipeline import simulate as simulate
from .pipeline import train as train
from .systems import NoiseModel as NoiseModel
from .systems import Signal as Signal
from .systems import System as System
from .systems import get_system as get_system

__version__ = "0.1.0"

