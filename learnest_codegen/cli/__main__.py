"""``python -m learnest_codegen.cli``: the ``learnest`` command."""

from . import main

main()
