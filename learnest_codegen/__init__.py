"""learnest_codegen: learned (KNODE) dynamics to compiled C state estimators.

Data flows one way: systems -> simulation/data -> observers -> training -> export ->
codegen -> toolchain -> runtime -> evaluation -> CLI.
"""

from .errors import LearnestError as LearnestError
from .systems import NoiseModel as NoiseModel
from .systems import Signal as Signal
from .systems import System as System
from .systems import get_system as get_system

__version__ = "0.1.0"
