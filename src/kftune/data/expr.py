"""Computed channels of an import mapping: a small arithmetic language over the columns of
a recording, parsed safely.

An expression (``"(wheel_fl + wheel_fr + wheel_rl + wheel_rr) / 4"``, ``"vx * omega"``) is
parsed with :func:`ast.parse` in ``"eval"`` mode and then checked node by node against a
whitelist: numbers, names, ``+ - * / **``, unary ``-`` and ``+``, parentheses, and calls of
the functions of :data:`FUNCTIONS` with positional arguments. Anything else (attribute
access, indexing, strings, lambdas, comprehensions, comparisons, keyword arguments, …) is
refused with a message naming it. The text is never given to Python's ``eval`` or
``compile``: :meth:`Expression.evaluate` walks the checked tree itself, on NumPy arrays.

Limits, so that hostile text costs nothing: at most :data:`MAX_CHARS` characters on one
line, nesting at most :data:`MAX_DEPTH` deep, and the exponent of ``**`` a number of
magnitude at most :data:`MAX_EXPONENT` (``10**10**10`` is refused before anything runs).

Names: ``t`` is the time [s] and ``pi`` is π; every other name is a value the caller
supplies (the importer: a channel of the mapping, in SI units, else a column of the file,
in the file's units). Values are float64 arrays of the recording's length; every operation
is element-wise. A division by zero or the square root of a negative number gives an
infinite or NaN sample, which validation then reports by row, like any bad sample.

Functions (``x`` an expression, ``c`` a number):

=================== ==========================================================================
``abs(x)``          \\|x\\|
``sqrt(x)``         √x (NaN where x < 0)
``sin cos tan(x)``  of x in radians
``atan2(y, x)``     the angle of (x, y) in radians, in (−π, π]
``mean(x1, …)``     the element-wise mean of its arguments, (x1 + … + xk) / k
``clip(x, lo, hi)`` x limited to [lo, hi] (lo ≤ hi, numbers)
``gradient(x)``     dx/dt per second: :func:`numpy.gradient` against t (second-order central
                    differences inside, one-sided at the ends); ``diff(x)`` is the same
``lowpass(x, c)``   x through a Butterworth low-pass of order :data:`LOWPASS_ORDER` with cut-off
                    c [Hz], run forward and backward (:func:`scipy.signal.filtfilt`: no phase
                    lag; the magnitude response squared, −6 dB at c); the sample rate is 1 /
                    the median step of t; c must lie below the Nyquist frequency
=================== ==========================================================================
"""

from __future__ import annotations

import ast
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from kftune.errors import KftuneError, excerpt

#: Most characters of one expression.
MAX_CHARS = 1000
#: Deepest nesting of the expression's tree (operators and calls within each other).
MAX_DEPTH = 40
#: Largest magnitude of the exponent of ``**`` (a number: x**2, x**0.5, x**-1).
MAX_EXPONENT = 64.0
#: Order of the Butterworth filter of ``lowpass`` (each pass; filtfilt runs two).
LOWPASS_ORDER = 2
#: Names that are not values of the recording: the time [s] and π.
RESERVED = ("t", "pi")

#: The most arguments ``mean`` takes (four wheel speeds need four; a longer list is a
#: mistake or an attempt on the memory).
MAX_MEAN_ARGS = 16

#: Function name → (fewest, most arguments; None: any number), what it computes.
FUNCTIONS: dict[str, tuple[int, int | None, str]] = {
    "abs": (1, 1, "|x|"),
    "sqrt": (1, 1, "square root"),
    "sin": (1, 1, "sine (radians)"),
    "cos": (1, 1, "cosine (radians)"),
    "tan": (1, 1, "tangent (radians)"),
    "atan2": (2, 2, "atan2(y, x) in radians"),
    "mean": (1, MAX_MEAN_ARGS, "element-wise mean of the arguments"),
    "clip": (3, 3, "clip(x, lo, hi)"),
    "gradient": (1, 1, "dx/dt per second"),
    "diff": (1, 1, "dx/dt per second (as gradient)"),
    "lowpass": (2, 2, "lowpass(x, cutoff_hz)"),
}

_BINARY: dict[type, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    ast.Add: np.add,
    ast.Sub: np.subtract,
    ast.Mult: np.multiply,
    ast.Div: np.divide,
    ast.Pow: np.power,
}
_UNARY: dict[type, Callable[[np.ndarray], np.ndarray]] = {
    ast.USub: np.negative,
    ast.UAdd: np.positive,
}
#: What a refused node is called in messages.
_REFUSED: dict[type, str] = {
    ast.Attribute: "attribute access (a.b)",
    ast.Subscript: "indexing (a[i])",
    ast.Lambda: "a lambda",
    ast.ListComp: "a comprehension",
    ast.SetComp: "a comprehension",
    ast.DictComp: "a comprehension",
    ast.GeneratorExp: "a comprehension",
    ast.Compare: "a comparison",
    ast.BoolOp: "and/or",
    ast.IfExp: "if/else",
    ast.List: "a list",
    ast.Tuple: "a tuple",
    ast.Dict: "a dict",
    ast.Set: "a set",
    ast.JoinedStr: "an f-string",
    ast.NamedExpr: "an assignment (:=)",
    ast.Starred: "*arguments",
    ast.Await: "await",
    ast.Yield: "yield",
    ast.YieldFrom: "yield",
    ast.FloorDiv: "// (floor division)",
    ast.Mod: "% (modulo)",
    ast.MatMult: "@",
    ast.BitAnd: "&",
    ast.BitOr: "|",
    ast.BitXor: "^",
    ast.LShift: "<<",
    ast.RShift: ">>",
    ast.Invert: "~",
    ast.Not: "not",
}
_ALLOWED = "numbers, names, + - * / **, parentheses and the functions " + ", ".join(FUNCTIONS)


class ExprError(KftuneError, ValueError):
    """An expression that is refused (parsing) or cannot be computed on these data.

    Attributes:
        index: the sample (0-based) at fault, when there is one.
    """

    def __init__(self, message: str, index: int | None = None) -> None:
        super().__init__(message)
        self.index = index


def _position(text: str, node: ast.AST) -> str:
    """``"at character 5"`` (1-based) of a node's start (``col_offset`` counts UTF-8 bytes)."""
    offset = getattr(node, "col_offset", None)
    if offset is None:
        return ""
    chars = len(text.encode("utf-8")[:offset].decode("utf-8", "ignore"))
    return f" at character {chars + 1}"


def _number(node: ast.AST) -> float | None:
    """The value of a literal number, optionally signed (``2``, ``-0.5``), else None."""
    sign = 1.0
    while isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        sign = -sign if isinstance(node.op, ast.USub) else sign
        node = node.operand
    constant = node.value if isinstance(node, ast.Constant) else None
    # not bool: True is an int to Python, not a number to a user
    if isinstance(constant, (int, float)) and not isinstance(constant, bool):
        try:
            value = float(constant)
        except OverflowError:
            return math.inf
        return sign * value
    return None


@dataclass(frozen=True)
class Expression:
    """A checked expression (make one with :func:`parse`).

    Attributes:
        text: the expression as written.
        names: the value names it refers to, in order of first appearance (without the
            :data:`RESERVED` ones).
    """

    text: str
    names: tuple[str, ...]
    tree: ast.expr

    def evaluate(self, values: Mapping[str, np.ndarray], t: np.ndarray) -> np.ndarray:
        """The expression's value at every sample.

        Args:
            values: name → (n,) float64 for every name of :attr:`names`.
            t: (n,) time [s], increasing.

        Returns:
            (n,) float64 (a constant expression gives a constant array).

        Raises:
            ExprError: a ``lowpass`` cut-off at or above the Nyquist frequency, a ``lowpass``
                of a signal with a NaN sample or too short for the filter, a ``gradient``
                of fewer than two samples.
        """
        t = np.asarray(t, dtype=np.float64)
        with np.errstate(all="ignore"):
            out = self._eval(self.tree, values, t)
        return np.array(np.broadcast_to(out, t.shape), dtype=np.float64)

    def _eval(self, node: ast.expr, values: Mapping[str, np.ndarray], t: np.ndarray) -> np.ndarray:
        if isinstance(node, ast.Constant):
            value = _number(node)
            if value is None:  # parse() refuses such a constant; an Expression made by hand
                raise ExprError(f"{excerpt(node.value)} is not a number; expected {_ALLOWED}")
            return np.float64(value)
        if isinstance(node, ast.Name):
            if node.id == "t":
                return t
            if node.id == "pi":
                return np.float64(math.pi)
            return np.asarray(values[node.id], dtype=np.float64)
        if isinstance(node, ast.UnaryOp):
            return _UNARY[type(node.op)](self._eval(node.operand, values, t))
        if isinstance(node, ast.BinOp):
            left = self._eval(node.left, values, t)
            return _BINARY[type(node.op)](left, self._eval(node.right, values, t))
        assert isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
        name = node.func.id
        if name == "mean":  # a running sum: one array at a time, not all of them stacked
            total = self._eval(node.args[0], values, t)
            for a in node.args[1:]:
                total = total + self._eval(a, values, t)
            return total / len(node.args)
        args = [self._eval(a, values, t) for a in node.args]
        if name == "abs":
            return np.abs(args[0])
        if name in ("sqrt", "sin", "cos", "tan"):
            return getattr(np, name)(args[0])
        if name == "atan2":
            return np.arctan2(args[0], args[1])
        if name == "clip":
            return np.clip(args[0], float(args[1]), float(args[2]))
        if name in ("gradient", "diff"):
            if t.size < 2:
                raise ExprError(f"{name}() needs at least 2 samples, got {t.size}")
            return np.gradient(np.broadcast_to(args[0], t.shape), t)
        return _lowpass(np.broadcast_to(args[0], t.shape), float(args[1]), t)


def _lowpass(x: np.ndarray, cutoff: float, t: np.ndarray) -> np.ndarray:
    """``x`` through a zero-phase Butterworth low-pass of cut-off ``cutoff`` [Hz] (order
    :data:`LOWPASS_ORDER`, forward and backward), at the sample rate 1 / median step of t."""
    from scipy import signal

    if t.size < 2:
        raise ExprError(f"lowpass() needs at least 2 samples, got {t.size}")
    step = float(np.median(np.diff(t)))
    nyquist = 0.5 / step if step > 0 else math.nan
    if not cutoff < nyquist:
        raise ExprError(
            f"lowpass() cut-off {cutoff:g} Hz is not below the Nyquist frequency "
            f"{nyquist:.4g} Hz of the recording (sample time {step:.4g} s): give a lower cut-off"
        )
    b, a = signal.butter(LOWPASS_ORDER, cutoff, btype="low", fs=1.0 / step)
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise ExprError(
            f"lowpass() of a signal with {bad.size} sample(s) that are not finite numbers "
            "(the filter would spread them over the whole recording)",
            index=int(bad[0]),
        )
    pad = 3 * max(len(a), len(b))
    if x.size <= pad:
        raise ExprError(f"lowpass() needs more than {pad} samples, got {x.size}")
    return signal.filtfilt(b, a, x)


def parse(text: str) -> Expression:
    """Parse and check an expression (see the module docstring).

    Raises:
        ExprError: not a string, too long, several lines, a syntax error (naming the
            position), a construct outside the whitelist (naming it and its position), an
            unknown function, a wrong number of arguments, an exponent that is not a number
            of magnitude at most :data:`MAX_EXPONENT`, nesting deeper than :data:`MAX_DEPTH`.
    """
    if not isinstance(text, str):
        raise ExprError(f"expected the expression as a string, got {excerpt(text)}")
    if not text.strip():
        raise ExprError("empty expression")
    if len(text) > MAX_CHARS:
        raise ExprError(f"expression of {len(text):,} characters; at most {MAX_CHARS:,}")
    if any(c in text for c in "\n\r\x00"):
        raise ExprError("expected the expression on one line")
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        where = f" at character {exc.offset}" if exc.offset else ""
        head = text.strip()[: max((exc.offset or 1) - 1, 0)]
        raise ExprError(
            f"syntax error{where} ({exc.msg}) in {excerpt(text.strip())}"
            + (f", after {excerpt(head)}" if head else "")
        ) from None
    except (RecursionError, MemoryError, ValueError):
        raise ExprError(f"expression nested more than {MAX_DEPTH} deep") from None
    names: dict[str, None] = {}
    _check(tree.body, text.strip(), names, 1)
    return Expression(text, tuple(names), tree.body)


def _check(node: ast.AST, text: str, names: dict[str, None], depth: int) -> None:
    """Refuse every node outside the whitelist; collect the names used (in ``names``)."""
    if depth > MAX_DEPTH:
        raise ExprError(f"expression nested more than {MAX_DEPTH} deep{_position(text, node)}")
    where = _position(text, node)
    if isinstance(node, ast.Constant):
        value = _number(node)
        if value is None:
            raise ExprError(f"{excerpt(node.value)}{where} is not a number; expected {_ALLOWED}")
        if not math.isfinite(value):
            raise ExprError(f"number{where} is too large")
        return
    if isinstance(node, ast.Name):
        if node.id in FUNCTIONS:
            raise ExprError(f"{node.id}{where} is a function: call it, {node.id}(…)")
        if node.id not in RESERVED:
            names.setdefault(node.id, None)
        return
    if isinstance(node, ast.UnaryOp) and type(node.op) in _UNARY:
        _check(node.operand, text, names, depth + 1)
        return
    if isinstance(node, ast.BinOp) and type(node.op) in _BINARY:
        if isinstance(node.op, ast.Pow):
            power = _number(node.right)
            if power is None or not abs(power) <= MAX_EXPONENT:
                raise ExprError(
                    f"the exponent of **{where} must be a number between {-MAX_EXPONENT:g} "
                    f"and {MAX_EXPONENT:g} (x**2, x**0.5), got {excerpt(ast.unparse(node.right))}"
                )
        _check(node.left, text, names, depth + 1)
        _check(node.right, text, names, depth + 1)
        return
    if isinstance(node, ast.Call):
        if not isinstance(node.func, ast.Name) or node.func.id not in FUNCTIONS:
            called = node.func.id if isinstance(node.func, ast.Name) else ast.unparse(node.func)
            raise ExprError(
                f"unknown function {excerpt(called)}{where}; expected one of {list(FUNCTIONS)}"
            )
        name = node.func.id
        if node.keywords or any(isinstance(a, ast.Starred) for a in node.args):
            raise ExprError(f"{name}(){where} takes positional arguments only")
        low, high, what = FUNCTIONS[name]
        n = len(node.args)
        if n < low or (high is not None and n > high):
            wanted = (
                f"at least {low}"
                if high is None
                else f"{low}"
                if low == high
                else f"{low} to {high}"
            )
            raise ExprError(f"{name}(){where} takes {wanted} argument(s) ({what}), got {n}")
        if name in ("clip", "lowpass"):
            given = [_number(a) for a in node.args[1:]]
            numbers = [v for v in given if v is not None and math.isfinite(v)]
            if len(numbers) < len(given):
                rest = "lo and hi" if name == "clip" else "the cut-off [Hz]"
                raise ExprError(f"{name}(){where}: {rest} must be numbers ({what})")
            if name == "clip" and not numbers[0] <= numbers[1]:
                raise ExprError(f"clip(){where}: lo must not exceed hi ({what})")
            if name == "lowpass" and not numbers[0] > 0:
                raise ExprError(f"lowpass(){where}: the cut-off must be > 0 Hz")
        for a in node.args:
            _check(a, text, names, depth + 1)
        return
    kind = _REFUSED.get(type(node))
    if kind is None and isinstance(node, (ast.BinOp, ast.UnaryOp)):
        kind = _REFUSED.get(type(node.op), type(node.op).__name__)
    raise ExprError(f"{kind or type(node).__name__}{where} is not allowed; expected {_ALLOWED}")
