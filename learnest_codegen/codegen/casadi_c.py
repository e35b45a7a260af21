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
# The lines of a CasADi SX function body that a batch (lane-parallel) copy can take over.
_BATCH_DECLARATION = re.compile(r"^  casadi_real (a\d+(, a\d+)*);$")
_BATCH_VOID = re.compile(r"^  \(void\)\w+;$")
_BATCH_INPUT = re.compile(r"^  (a\d+)=arg\[(\d+)\]\? arg\[\2\]\[(\d+)\] : 0;$")
_BATCH_CONSTANT = re.compile(r"^  (a\d+)=([-+]?\d+\.?\d*(?:[eE][-+]?\d+)?);$")
_BATCH_EXPRESSION = re.compile(r"^  (a\d+)=([-+*/() .\w]+);$")
_BATCH_OUTPUT = re.compile(r"^  if \(res\[(\d+)\]!=0\) res\[\1\]\[(\d+)\]=(a\d+);$")
# Names an expression may use: variables, literals and the routines learnest_simd.h has.
_BATCH_TOKEN = re.compile(r"a\d+|\d+\.?\d*(?:[eE][-+]?\d+)?|learnest_(?:tanh|sin|cos|fabs)|casadi_sq")
_BATCH_ROUTINE = re.compile(r"\b(?:learnest_(tanh|sin|cos|fabs)|casadi_(sq))\(")
#: Points a batch function evaluates at once: one 32-byte vector of reals (learnest_simd.h).
BATCH_LANES = {"float64": 4, "float32": 8}
#: The largest function (CasADi's ``n_instructions``) that gets a batch copy: compiling its two
#: vector builds takes GCC 12 -O2 about 3 s of CPU at 2,500 operations (the demo's stage) and
#: 15 s at 8,000 (a 32-unit net), against 0.3 s and 1.2 s for the scalar code.
BATCH_MAX_INSTRUCTIONS = 5000



def write_casadi_c(functions: Sequence[cs.Function], directory: Path, name: str,
                   precision: str, batch: Sequence[str] = ()) -> tuple[Path, Path]:
    """``directory/<name>.c`` and ``.h``: CasADi's code of ``functions`` in ``precision``.

    For each function named in ``batch`` of at most ``BATCH_MAX_INSTRUCTIONS`` operations whose
    code :func:`batch_body` can take over, it also
    writes ``<function>_batch(arg, res)``: the function on ``BATCH_LANES[precision]`` points at
    once (input and output entry ``j`` of point ``l`` at ``[j * lanes + l]``), compiled where
    learnest_simd.h has vectors; the header then defines ``<function>_BATCH_LANES``.
    """
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
    small = {f.name() for f in functions
             if f.name() in batch and f.n_instructions() <= BATCH_MAX_INSTRUCTIONS}
    batches = [(f, body) for f in batch
               if f in small and (body := batch_body(text, f, precision)) is not None]
    if batches:
        text = _append_batches(text, batches, precision)
        header = source.with_suffix(".h")
        header.write_text(_declare_batches(header.read_text(), [f for f, _ in batches],
                                           BATCH_LANES[precision]))
    source.write_text(text)
    return source, source.with_suffix(".h")


def batch_body(text: str, function: str, precision: str) -> list[str] | None:
    """The body of ``function``'s lane-parallel copy, or None where its code has a line that
    is not a plain scalar assignment of + - * / and the routines of learnest_simd.h."""
    call = re.search(rf"^CASADI_SYMBOL_EXPORT int {function}\(.*\{{\n  return (\w+)\(", text, re.M)
    if call is None:
        return None
    start = re.search(rf"^static int {call.group(1)}\(.*\{{$", text, re.M)
    if start is None:
        return None
    lines = text[start.end() + 1:].split("\n")
    kind = "d" if precision == "float64" else "f"
    lanes = BATCH_LANES[precision]
    vector = "learnest_v4d" if kind == "d" else "learnest_v8f"
    out = []
    for line in lines[:lines.index("}")]:
        if _BATCH_VOID.match(line) or line == "  return 0;":
            continue
        if m := _BATCH_DECLARATION.match(line):
            out.append(f"  {vector} {m.group(1)};")
        elif m := _BATCH_INPUT.match(line):
            out.append(f"  memcpy(&{m.group(1)}, arg[{m.group(2)}] + {int(m.group(3)) * lanes}, "
                       f"sizeof {m.group(1)});")
        elif m := _BATCH_CONSTANT.match(line):
            out.append(f"  {m.group(1)}=learnest_vdup_{kind}({m.group(2)});")
        elif m := _BATCH_OUTPUT.match(line):
            out.append(f"  if (res[{m.group(1)}]) memcpy(res[{m.group(1)}] + {int(m.group(2)) * lanes}, "
                       f"&{m.group(3)}, sizeof {m.group(3)});")
        elif (m := _BATCH_EXPRESSION.match(line)) and _only_batch_tokens(m.group(2)):
            expression = _BATCH_ROUTINE.sub(
                lambda r: f"learnest_v{r.group(1) or r.group(2)}_{kind}(", m.group(2))
            out.append(f"  {m.group(1)}={expression};")
        else:
            return None
    return out


def _only_batch_tokens(expression: str) -> bool:
    words = re.findall(r"[A-Za-z_]\w*|\d+\.?\d*(?:[eE][-+]?\d+)?", expression)
    return all(_BATCH_TOKEN.fullmatch(w) for w in words)


_BATCH_END = '#ifdef __cplusplus\n} /* extern "C" */\n#endif'


def _append_batches(text: str, batches: list[tuple[str, list[str]]], precision: str) -> str:
    lanes = BATCH_LANES[precision]
    code = ['#include "learnest_simd.h"', "", "#if LEARNEST_SIMD"]
    for function, body in batches:
        code += [f"/* {function} on {lanes} points at once, each lane the scalar code's operations "
                 "(learnest_simd.h). */",
                 f"LEARNEST_SIMD_BATCH int {function}_batch(const casadi_real** arg, casadi_real** res) {{",
                 *body, "  return 0;", "}", ""]
    code += ["#endif /* LEARNEST_SIMD */", ""]
    if _BATCH_END not in text:
        raise BuildError(f"CasADi {cs.__version__} wrote C without the closing {_BATCH_END!r}; "
                         "update codegen/casadi_c.py")
    head, tail = text.rsplit(_BATCH_END, 1)
    return head + "\n".join(code) + "\n" + _BATCH_END + tail


def _declare_batches(header: str, functions: list[str], lanes: int) -> str:
    lines = []
    for function in functions:
        lines += [f"int {function}_batch(const casadi_real** arg, casadi_real** res);",
                  f"#define {function}_BATCH_LANES {lanes}"]
    head, tail = header.rsplit(_BATCH_END, 1)
    return head + "\n".join(lines) + "\n" + _BATCH_END + tail


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
