"""The ``learnest`` command line (and ``learnest-compile``): one module per group of commands.

Commands: ``simulate``, ``train``, ``compile``, ``estimate``, ``evaluate``, ``demo``, ``reproduce table1``,
``reproduce quadrotor``, ``diagnose``.
Every ``--system`` accepts a built-in name or the path of a Python file defining ``SYSTEM``.
Errors a user can cause (the package's :class:`LearnestError`, missing or unwritable files,
values out of range) are printed as one clear line with exit code 1 instead of a traceback;
``LEARNEST_TRACEBACK=1`` shows the traceback. Outputs are never written over an input, nor over
an existing file or folder without ``--force``, and appear whole or not at all.
"""

from __future__ import annotations

import click

from .common import USER_ERRORS as USER_ERRORS
from .diagnose import diagnose
from .estimation import compile_cmd, estimate
from .evaluation import evaluate
from .experiments import demo, reproduce
from .modelling import simulate, train


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="learnest_codegen")
def cli() -> None:
    """Learned (KNODE) dynamics models to compiled C state estimators (MHE, UKF)."""


for _command in (simulate, train, compile_cmd, estimate, evaluate, demo, reproduce, diagnose):
    cli.add_command(_command)


def main() -> None:
    """Entry point of ``learnest``."""
    cli(prog_name="learnest")


def compile_main() -> None:
    """Entry point of ``learnest-compile``: ``learnest compile`` under its own program name."""
    compile_cmd(prog_name="learnest-compile")

