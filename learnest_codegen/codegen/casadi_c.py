"""CasADi's generated C, written so that it compiles clean everywhere the kit does.

CasADi gives every generated function its calling convention ``(arg, res, iw, w, mem)`` and
leaves the arguments a function does not need unused, which ``-Wextra`` reports (CasADi 3.8
has no option against it); its Ipopt interface passes string literals as ``char*``, which
C++ refuses. :func:`write_casadi_c` writes the file with CasADi's ``CodeGenerator`` and then
marks each unused parameter ``(void)name;`` and casts those literals, so the generated folder
builds under ``-Wall -Wextra -Werror -pedantic`` with gcc, clang and g++ without a per-file
flag (tested in tests/test_handoff.py). It also includes the kit's ``learnest_math.h`` after
CasADi's definitions and renames CasADi's calls of the C math routines (``sin(``, ``tanh(``,
...) to the kit's ``learnest_sin(``, ...: the one place where a build's math routines are
chosen by precision (a float32 build calls float routines; docs/reports/cortex_m.md). In a
float32 build it writes CasADi's integral double operands ``(2.*a)`` and ``(1./a)`` as ``(2*a)``
and ``(1/a)``: the same float result (a product or quotient of floats computed in double and
rounded to float is the correctly rounded float one), without promoting ``a`` to double, which
``-Wdouble-promotion`` rejects (the Crazyflie firmware builds with it and ``-Werror``; gcc -O2
folds the promotion away, so the code it makes is the same).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

import casadi as cs

from ..errors import BuildError
from ..estimators.precision import PRECISIONS

# A function definition on one line, as CasADi writes every one: "<type> name(params) {".
_DEFINITION = re.compile(r"^[A-Za-z_][\w \*]*?\b\w+\((?P<params>[^()]*)\)\s*\{\s*$")
_IDENTIFIER = re.compile(r"[A-Za-z_]\w*")
_IPOPT_OPTION = re.compile(r"AddIpopt\w+Option\(")
_STRING = re.compile(r'"([^"\\]*)"')
# After CasADi's "#define casadi_int ..." block: the model code's math routines (learnest_math.h).
_MATH_ANCHOR = "/* Add prefix to internal symbols */"
_MATH = '#define LEARNEST_REAL casadi_real\n#include "learnest_math.h"\n\n'
# The C math routines CasADi 3.8 calls by name; each is learnest_<name> in learnest_math.h.
MATH_ROUTINES = ("sin", "cos", "tan", "tanh", "exp", "log", "sqrt", "fabs", "asin", "acos",
                 "atan", "sinh", "cosh", "asinh", "acosh", "atanh", "log1p", "expm1", "floor",
                 "ceil", "erf", "atan2", "pow", "fmod", "fmin", "fmax", "hypot", "copysign")
_MATH_CALL = re.compile(r"(?<![\w.\"])(" + "|".join(MATH_ROUTINES) + r")(?=\s*\()")
# CasADi writes some operations with an integral double literal as operand, "(2.*a)" (twice)
# and "(1./a)" (inverse), which in a float build promote the float operand to double.
_INTEGRAL_OPERAND = re.compile(r"\((\d+)\.([*/])")



def write_casadi_c(functions: Sequence[cs.Function], directory: Path, name: str,
                   precision: str) -> tuple[Path, Path]:
    """``directory/<name>.c`` and ``.h``: CasADi's code of ``functions`` in ``precision``."""
    generator = cs.CodeGenerator(f"{name}.c", {"with_header": True,
                                               "casadi_real": PRECISIONS[precision]})
    for function in functions:
        generator.add(function)
    generator.generate(f"{directory}/")
    source = Path(directory) / f"{name}.c"
    text = clean(source.read_text())
    if precision == "float32":
        head, tail = text.split(_MATH_ANCHOR, 1)
        text = head + _MATH_ANCHOR + _INTEGRAL_OPERAND.sub(r"(\1\2", tail)
    source.write_text(text)
    return source, source.with_suffix(".h")


def clean(text: str) -> str:
    """``text`` with every unused parameter marked used and Ipopt's option names cast."""
    lines = text.split("\n")
    out: list[str] = []
    for i, line in enumerate(lines):
        out.append(_cast_strings(line) if _IPOPT_OPTION.search(line) else line)
        match = _DEFINITION.match(line)
        if match:
            body = _body(lines, i + 1)
            used = set(_IDENTIFIER.findall(body))
            for param in _parameter_names(match.group("params")):
                if param not in used:
                    out.append(f"  (void){param};")
    text = "\n".join(out)
    if _MATH_ANCHOR not in text:
        raise BuildError(f"CasADi {cs.__version__} wrote C without the line {_MATH_ANCHOR!r}, "
                         "after which learnest_math.h is included; update codegen/casadi_c.py")
    head, tail = text.split(_MATH_ANCHOR, 1)
    return head + _MATH + _MATH_ANCHOR + _MATH_CALL.sub(r"learnest_\1", tail)


def _parameter_names(params: str) -> list[str]:
    names = []
    for param in params.split(","):
        words = _IDENTIFIER.findall(param.split("[")[0])
        if words and words != ["void"]:
            names.append(words[-1])
    return names


def _body(lines: list[str], start: int) -> str:
    """The lines of a function body from ``start`` to its closing ``}`` in column 0."""
    end = start
    while end < len(lines) and not lines[end].startswith("}"):
        end += 1
    return "\n".join(lines[start:end])


def _cast_strings(line: str) -> str:
    return _STRING.sub(lambda m: f'(char*)"{m.group(1)}"', line)
