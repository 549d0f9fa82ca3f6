"""The C contract of a model: what ``kftune export --format c`` needs from a model's C code.

A model is exported as a running filter through :attr:`StateSpaceModel.c_code
<kftune.models.base.StateSpaceModel.c_code>`, the C99 source text of its hooks. That text
includes ``kftune_model.h``, the header :func:`model_header` writes for the model: the
scalar type ``kf_real`` (``double``, or ``float`` for ``--precision float``), the sizes
(``KF_N``, ``KF_M``, ``KF_NU``, ``KF_NW``, ``KF_NP``, ``KF_NHELD``, ``KF_NOUT``), which
optional hooks the model has (``KF_HAS_PREPARE``, ``KF_HAS_F_JACOBIAN``,
``KF_HAS_H_JACOBIAN``, ``KF_HAS_CHECK``), an index macro per name (``KF_X_<STATE>``,
``KF_Z_<MEASUREMENT>``, ``KF_U_<INPUT>``, ``KF_P_<PARAM>``, ``KF_Y_<OUTPUT>``) and the
prototypes the C must define — each the twin of a Python hook (:mod:`kftune.models.base`)
with the same arguments, arrays flat and matrices row-major:

    kf_model_prior(z0, r, p, x0, P0)      model.initial_state(z0, r, p) -> (x0, P0)
    kf_model_f(x, w, p, dt, out)          model.f, w the prepared input row
    kf_model_h(x, w, p, out)              model.h
    kf_model_outputs(x, y)                model.outputs, KF_NOUT values of one state
    kf_model_prepare(u_raw, p, w)         model.prepare        (KF_HAS_PREPARE)
    kf_model_F(x, w, p, dt, out)          model.F, KF_N·KF_N   (KF_HAS_F_JACOBIAN)
    kf_model_H(x, w, p, out)              model.H, KF_M·KF_N   (KF_HAS_H_JACOBIAN)
    kf_model_check(x, z, w, p, held)      model.check: 0 or a stop cause >= 2, held[j] set
                                          (KF_HAS_CHECK)

The header includes ``<tgmath.h>``: ``sin``, ``atan2``, ``fabs`` … are type-generic, so one
model source computes in ``float`` when ``kf_real`` is ``float``. Each hook must reproduce
its Python twin to rounding (about 1e-13 relative on real data), because the exported
filter is held to 1e-9 of ``kftune estimate``; :func:`missing_hooks` names the functions a
model's C does not define, so that an export can refuse it by name.

The built-in models' C lives in package data, ``kftune/models/c/<name>.c``
(:func:`builtin_c_code`).
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Sequence
from pathlib import Path

from kftune.models.base import StateSpaceModel

__all__ = [
    "C_REALS",
    "OPTIONAL_HOOKS",
    "REQUIRED_HOOKS",
    "builtin_c_code",
    "builtin_names",
    "c_identifier",
    "defined_functions",
    "export_refusal",
    "missing_hooks",
    "model_header",
    "required_hooks",
]

#: The scalar types the header can declare as ``kf_real``.
C_REALS = ("double", "float")

#: The functions every exported model's C defines.
REQUIRED_HOOKS = ("kf_model_prior", "kf_model_f", "kf_model_h", "kf_model_outputs")
#: Optional Python hook (attribute of the model) → its C function and the header's flag.
OPTIONAL_HOOKS: dict[str, tuple[str, str]] = {
    "prepare": ("kf_model_prepare", "KF_HAS_PREPARE"),
    "F": ("kf_model_F", "KF_HAS_F_JACOBIAN"),
    "H": ("kf_model_H", "KF_HAS_H_JACOBIAN"),
    "check": ("kf_model_check", "KF_HAS_CHECK"),
}

_PROTOTYPES: dict[str, str] = {
    "kf_model_prior": "void kf_model_prior(const kf_real z0[], const kf_real r[], "
    "const kf_real p[], kf_real x0[], kf_real P0[]);",
    "kf_model_f": "void kf_model_f(const kf_real x[], const kf_real w[], const kf_real p[], "
    "kf_real dt, kf_real out[]);",
    "kf_model_h": "void kf_model_h(const kf_real x[], const kf_real w[], const kf_real p[], "
    "kf_real out[]);",
    "kf_model_outputs": "void kf_model_outputs(const kf_real x[], kf_real y[]);",
    "kf_model_prepare": "void kf_model_prepare(const kf_real u_raw[], const kf_real p[], "
    "kf_real w[]);",
    "kf_model_F": "void kf_model_F(const kf_real x[], const kf_real w[], const kf_real p[], "
    "kf_real dt, kf_real out[]);",
    "kf_model_H": "void kf_model_H(const kf_real x[], const kf_real w[], const kf_real p[], "
    "kf_real out[]);",
    "kf_model_check": "int kf_model_check(const kf_real x[], const kf_real z[], "
    "const kf_real w[], const kf_real p[], int held[]);",
}
_PROTOTYPE_NOTES: dict[str, str] = {
    "kf_model_prior": "x0: KF_N, P0: KF_N*KF_N row-major; model.initial_state(z0, r, p)",
    "kf_model_f": "out: KF_N = x one step dt [s] on; w: the prepared input row (KF_NW)",
    "kf_model_h": "out: KF_M, the measurement predicted for x and w",
    "kf_model_outputs": "y: KF_NOUT values of one state, in the KF_Y_ order",
    "kf_model_prepare": "w: KF_NW, the prepared row of a raw input row u_raw (KF_NU)",
    "kf_model_F": "out: KF_N*KF_N row-major, df/dx",
    "kf_model_H": "out: KF_M*KF_N row-major, dh/dx",
    "kf_model_check": "0 (valid) or a stop cause >= 2; held[j] = 1 while held condition j "
    "is violated (KF_NHELD)",
}


def c_identifier(name: str) -> str:
    """An upper-case C identifier fragment of a model's name: ASCII letters and digits
    kept, any other ASCII character → ``_`` (runs collapsed, none at the ends), a
    non-ASCII character → ``U`` and its code point (``β`` → ``U03B2``).

    Raises:
        ValueError: ``name`` has no letter, digit or non-ASCII character.
    """
    parts = []
    for ch in name:
        if ch.isascii():
            parts.append(ch.upper() if ch.isalnum() else "_")
        else:
            parts.append(f"_U{ord(ch):04X}_")
    ident = re.sub(r"_+", "_", "".join(parts)).strip("_")
    if not ident:
        raise ValueError(
            f"name {name!r} gives no C identifier: it needs a letter or a digit for its "
            "index macro in kftune_model.h"
        )
    return ident


def _index_macros(
    model: StateSpaceModel, prefix: str, what: str, names: Sequence[str]
) -> list[str]:
    """``#define <prefix><NAME> i`` for each name; ValueError on a collision."""
    seen: dict[str, str] = {}
    lines = []
    for i, name in enumerate(names):
        macro = prefix + c_identifier(name)
        if macro in seen:
            raise ValueError(
                f"model {model.name!r}: {what} names {seen[macro]!r} and {name!r} both give the "
                f"C macro {macro} in kftune_model.h; rename one so that they differ in more "
                "than case and punctuation"
            )
        seen[macro] = name
        lines.append(f"#define {macro} {i}")
    return lines


def _comment(text: str) -> str:
    """``text`` safe inside a C block comment."""
    return text.replace("*/", "* /").replace("/*", "/ *")


def _name_list(names: Sequence[str], units: Sequence[str]) -> str:
    items = [f"{n} [{u}]" if u else n for n, u in zip(names, units, strict=True)]
    return ", ".join(items) if items else "(none)"


def _hook_flags(model: StateSpaceModel) -> dict[str, int]:
    return {
        flag: int(getattr(model, hook) is not None) for hook, (_, flag) in OPTIONAL_HOOKS.items()
    }


def model_header(model: StateSpaceModel, real: str = "double") -> str:
    """The text of ``kftune_model.h`` for ``model`` (module docstring): include guard
    ``KFTUNE_MODEL_H``, ``<tgmath.h>``, ``typedef <real> kf_real;``, sizes, hook flags,
    the names with units and index macros, and the prototypes of the contract.

    Args:
        model: the model; real: ``"double"`` or ``"float"``.

    Raises:
        ValueError: ``real`` is not a C real type of :data:`C_REALS`, or two names of one
            kind give the same index macro.
    """
    if real not in C_REALS:
        raise ValueError(f"real must be one of {', '.join(C_REALS)}, got {real!r}")
    n_w = model.prepared_size if model.prepare is not None else model.n_inputs
    n_held = len(model.held_causes)
    outputs = list(model.outputs)
    flags = _hook_flags(model)
    sizes = {
        "KF_N": (model.n_states, "states"),
        "KF_M": (model.n_measurements, "measurements"),
        "KF_NU": (model.n_inputs, "raw inputs (a row of the data's input channels)"),
        "KF_NW": (n_w, "prepared input row (= KF_NU without a prepare hook)"),
        "KF_NP": (model.n_params, "parameters"),
        "KF_NHELD": (n_held, "held conditions of kf_model_check"),
        "KF_NOUT": (len(outputs), "outputs"),
    }
    lines = [
        "/* kftune_model.h: the C contract of the kftune model "
        f'"{_comment(model.name)}", written by kftune.',
        " * The model's C (kftune_model.c) includes it and defines the functions declared",
        " * at the end, each the twin of the model's Python hook: arrays are flat, matrices",
        " * row-major, units SI as named below. */",
        "#ifndef KFTUNE_MODEL_H",
        "#define KFTUNE_MODEL_H",
        "",
        "/* type-generic math: sin, atan2, fabs ... take kf_real, float or double */",
        "#include <tgmath.h>",
        "",
        f"typedef {real} kf_real;",
        f"#define KF_REAL_IS_DOUBLE {int(real == 'double')}",
        "",
        "/* sizes */",
    ]
    for macro, (value, what) in sizes.items():
        lines.append(f"#define {macro} {value} /* {what} */")
    lines.append("/* array sizes of the above that may be 0 (C has no zero-length arrays) */")
    for macro in ("KF_NU", "KF_NW", "KF_NP", "KF_NHELD", "KF_NOUT"):
        lines.append(f"#define {macro}_ARR ({macro} > 0 ? {macro} : 1)")
    lines += ["", "/* hooks the model has (1) or not (0) */"]
    lines += [f"#define {flag} {value}" for flag, value in flags.items()]
    held = ", ".join(str(c) for c in model.held_causes) or "none"
    lines.append(f"/* stop cause of each held condition j: {held} */")
    groups = (
        ("KF_X_", "state", "states", model.state_names, model.state_units),
        ("KF_Z_", "measurement", "measurements", model.measurement_names, model.measurement_units),
        ("KF_U_", "input", "raw inputs", model.input_names, model.input_units),
        ("KF_P_", "parameter", "parameters p", model.param_names, model.param_units),
        ("KF_Y_", "output", "outputs", outputs, ("",) * len(outputs)),
    )
    for prefix, what, title, names, units in groups:
        lines += ["", f"/* {title}: {_comment(_name_list(names, units))} */"]
        lines += _index_macros(model, prefix, what, names)
    lines += ["", "/* the model's functions (kftune_model.c) */"]
    for fn in REQUIRED_HOOKS:
        lines += [f"/* {_PROTOTYPE_NOTES[fn]} */", _PROTOTYPES[fn]]
    for fn, flag in (v for v in OPTIONAL_HOOKS.values()):
        lines += [f"#if {flag}", f"/* {_PROTOTYPE_NOTES[fn]} */", _PROTOTYPES[fn], "#endif"]
    lines += ["", "#endif /* KFTUNE_MODEL_H */", ""]
    return "\n".join(lines)


def required_hooks(model: StateSpaceModel) -> list[str]:
    """The contract's functions ``model``'s C must define: the prior, f, h and the
    outputs always, and each optional hook the Python model has."""
    flags = _hook_flags(model)
    return [*REQUIRED_HOOKS, *(fn for fn, flag in OPTIONAL_HOOKS.values() if flags[flag])]


def _strip_comments(code: str) -> str:
    """C source without its comments (string literals are not expected in a model)."""
    return re.sub(r"/\*.*?\*/|//[^\n]*", " ", code, flags=re.S)


def defined_functions(code: str, names: Iterable[str]) -> set[str]:
    """Which of ``names`` the C source ``code`` defines: a name followed by its
    parenthesised arguments and a body ``{`` (not a prototype ``;`` or a call)."""
    text = _strip_comments(code)
    return {
        name for name in names if re.search(rf"\b{re.escape(name)}\s*\([^;{{}}]*\)\s*\{{", text)
    }


def missing_hooks(model: StateSpaceModel) -> list[str]:
    """The contract's functions ``model.c_code`` must define but does not (all of them
    without c_code), in the contract's order."""
    wanted = required_hooks(model)
    found = defined_functions(model.c_code or "", wanted)
    return [fn for fn in wanted if fn not in found]


def export_refusal(model: StateSpaceModel) -> str | None:
    """Why ``model`` cannot be exported as C, in a sentence naming the model and what to
    give it; None when it can (c_code defines every function the contract asks)."""
    how = (
        "give the StateSpaceModel c_code=<C99 source of its hooks> written against "
        "kftune_model.h (README: 'A model of your own in C')"
    )
    if model.c_code is None:
        return f"model {model.name!r} has no C code (c_code is None): {how}"
    if model.initial_state is None:
        return (
            f"model {model.name!r} has no prior rule (initial_state), which the exported "
            "filter needs at step 0 as kf_model_prior"
        )
    missing = missing_hooks(model)
    if missing:
        return (
            f"model {model.name!r}: its c_code does not define {', '.join(missing)} "
            f"(the contract's functions for the hooks the Python model has); {how}"
        )
    try:
        model_header(model)
    except ValueError as exc:
        return str(exc)
    return None


#: The built-in models' C files, package data beside this module.
_C_FOLDER = Path(__file__).resolve().parent / "c"


def builtin_names() -> list[str]:
    """The names of the built-in models' C files (``kftune/models/c/<name>.c``)."""
    folder = _C_FOLDER
    if not folder.is_dir():
        return []
    return sorted(p.name[:-2] for p in folder.iterdir() if p.name.endswith(".c"))


def builtin_c_code(name: str) -> str:
    """The text of the built-in C file ``kftune/models/c/<name>.c`` (package data).

    Raises:
        ValueError: no such file (the message lists those there are).
    """
    path = _C_FOLDER / f"{name}.c"
    if not re.fullmatch(r"[A-Za-z0-9_\-]+", name) or not path.is_file():
        raise ValueError(
            f"no built-in model C file {name!r}; there are: {', '.join(builtin_names())}"
        )
    return path.read_text(encoding="utf-8")
