"""A tuned filter for deployment: one flat mapping, written as JSON, YAML, a C header or a
MATLAB script (``kftune export``).

:func:`export_document` collects from a tuned-parameters file what embedded code needs —
model, filter, sample time dt [s], Q and R diagonals (Q per step of dt), state, input and
measurement names with units, sigma-point settings, the model's parameter vector, the
vehicle, the initial-state rule and the provenance (dataset fingerprint, method, kftune
version) — as a mapping whose values are numbers, strings, null or flat lists of them.
The four writers render that one mapping, so they agree by construction; every float is
written with Python's ``repr`` (the shortest text that reads back as the same double).

A calibrated filter (``tune`` fitted a covariance scale c, :mod:`kftune.tuning.calibrate`)
runs with ``q_diag`` and ``r_diag`` as tuned; ``covariance_scale`` (c) multiplies every
covariance it reports (P, and S for the NIS and gating), so that its σ matches its errors.

The YAML is written by hand (the mapping is flat; PyYAML is not a dependency): keys
plain, strings double-quoted with JSON escapes, floats always with a decimal point and a
signed exponent so that YAML 1.1 readers (PyYAML) read them as floats, not strings.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

from kftune import __version__
from kftune.errors import DataError
from kftune.vehicle.params import PLAUSIBLE_RANGES

#: The ``format`` of an exported filter.
EXPORT_FORMAT = "kftune-filter-1"
#: What ``kftune export --format`` writes.
EXPORT_FORMATS = ("json", "yaml", "c", "matlab")

#: Units of the vehicle parameters (VehicleParams), for comments.
VEHICLE_UNITS = {name: unit for name, (_, _, unit) in PLAUSIBLE_RANGES.items()}


def export_document(tuned: Mapping[str, Any], source: str) -> dict[str, Any]:
    """The flat mapping of a tuned-parameters file (as read by
    :func:`kftune.cli.evaluate.read_tuned`).

    Raises:
        DataError: naming ``source``, when the file predates the ``deployment`` record (it
            lacks the sample time and vehicle a deployment needs) or the record is damaged.
    """
    dep = tuned.get("deployment")
    if not isinstance(dep, Mapping):
        raise DataError(
            "records no 'deployment' (sample time, vehicle, units): it was written by a "
            "kftune older than 'kftune export'; tune again to write one (the study, if you "
            "kept it, resumes: kftune tune --storage STUDY --resume)",
            file=source,
        )
    try:
        states, state_units = _names(dep["states"])
        inputs, input_units = _names(dep["inputs"])
        meas, meas_units = _names(dep["measurements"])
        q = {e["name"]: (float(e["variance"]), str(e["unit"])) for e in dep["Q"]}
        r = {e["name"]: (float(e["variance"]), str(e["unit"])) for e in dep["R"]}
        doc: dict[str, Any] = {
            "format": EXPORT_FORMAT,
            "model": str(dep["model"]),
            "filter": str(dep["filter"]),
            "dt": float(dep["dt"]),
            "states": states,
            "state_units": state_units,
            "inputs": inputs,
            "input_units": input_units,
            "measurements": meas,
            "measurement_units": meas_units,
            "q_diag": [q[s][0] for s in states],
            "q_units": [q[s][1] for s in states],
            "r_diag": [r[s][0] for s in meas],
            "r_units": [r[s][1] for s in meas],
        }
        sp = dep["sigma_points"]
        if sp is not None:
            doc.update(
                ukf_alpha=float(sp["alpha"]),
                ukf_beta=float(sp["beta"]),
                ukf_kappa=float(sp["kappa"]),
                sigma_points=str(sp.get("convention", "")),
            )
        mp = dep["model_params"]
        doc["model_param_names"] = [str(e["name"]) for e in mp]
        doc["model_param_units"] = [str(e["unit"]) for e in mp]
        doc["model_params"] = [float(e["value"]) for e in mp]
        tuned_mp = tuned.get("model_params") or {}
        if tuned_mp:  # tuned with the noise: the values above are the tuned ones
            from kftune.tuning.deploy import tuned_model_params

            tuned_model_params(tuned, source, doc["model_param_names"])  # names checked
            doc["tuned_model_param_names"] = [str(n) for n in tuned_mp]
            doc["tuned_model_param_starts"] = [float(e["start"]) for e in tuned_mp.values()]
        if dep["vehicle"] is not None:  # None: a model that is not a car's
            vehicle = dict(dep["vehicle"])
            doc["vehicle_name"] = str(vehicle.pop("name", ""))
            for key, value in vehicle.items():
                doc[f"vehicle_{key}"] = None if value is None else float(value)
        doc["initial_state"] = str(dep["initial_state"])
        cal = dep.get("calibration")
        if cal is not None:  # the reported covariances' factor; Q and R run as they are
            doc["covariance_scale"] = float(cal["factor"])
        ds = dep["dataset"]
        doc.update(
            dataset=str(ds["name"]),
            dataset_sha256=str(ds["sha256"]),
            dataset_manoeuvres=int(ds["n_manoeuvres"]),
            dataset_samples=int(ds["n_samples"]),
        )
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise DataError(
            f"the 'deployment' record is damaged ({type(exc).__name__}: {exc})", file=source
        ) from None
    if len(doc["q_diag"]) != len(tuned.get("q", doc["q_diag"])):
        raise DataError("'deployment.Q' does not match 'q'", file=source)
    for key in ("method", "seed", "cost"):
        if key in tuned:
            doc[f"tuned_{key}"] = tuned[key]
    doc["tuned_with"] = f"kftune {tuned.get('kftune_version', '?')}"
    doc["exported_with"] = f"kftune {__version__}"
    for key, value in doc.items():
        values = value if isinstance(value, list) else [value]
        if any(isinstance(v, float) and not math.isfinite(v) for v in values):
            raise DataError(f"{key} is not finite", file=source)
    return doc


def _names(entries: Sequence[Mapping[str, Any]]) -> tuple[list[str], list[str]]:
    return [str(e["name"]) for e in entries], [str(e["unit"]) for e in entries]


def _float(v: float) -> str:
    """``repr`` of a float: the shortest decimal that reads back as the same double."""
    return repr(float(v))


# -- JSON and YAML -------------------------------------------------------------------------


def to_json(doc: Mapping[str, Any]) -> str:
    """Strict JSON, one key per line."""
    return json.dumps(doc, indent=1, allow_nan=False) + "\n"


def _yaml_scalar(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        text = _float(v)
        mantissa, e, exponent = text.partition("e")
        if "." not in mantissa:
            mantissa += ".0"
        if e and exponent[0] not in "+-":
            exponent = "+" + exponent
        return mantissa + (f"e{exponent}" if e else "")
    return json.dumps(str(v))  # JSON escapes are YAML double-quoted escapes


def to_yaml(doc: Mapping[str, Any], header: str = "") -> str:
    """The flat mapping as YAML (module docstring); ``header`` as comment lines."""
    lines = [f"# {line}".rstrip() for line in header.splitlines()]
    for key, value in doc.items():
        if isinstance(value, list):
            text = "[" + ", ".join(_yaml_scalar(v) for v in value) + "]"
        else:
            text = _yaml_scalar(value)
        lines.append(f"{key}: {text}")
    return "\n".join(lines) + "\n"


# -- C -------------------------------------------------------------------------------------


def _c_name(text: str) -> str:
    """An upper-case C identifier part from a name (``"C_af"`` → ``"C_AF"``)."""
    out = re.sub(r"[^0-9A-Za-z]+", "_", text).strip("_").upper()
    return out if out and not out[0].isdigit() else f"_{out}"


def _c_comment(text: str) -> str:
    """Text safe inside a C block comment (no ``*/`` or ``/*``; ASCII; one line, so that
    it can sit in a macro continued over lines)."""
    text = " ".join(text.splitlines()).replace("*/", "* /").replace("/*", "/ *")
    for char, plain in _ASCII.items():
        text = text.replace(char, plain)
    return text.encode("ascii", "replace").decode()


#: Symbols of kftune's texts in plain ASCII (C comments).
_ASCII = {
    "·": "*", "²": "^2", "β": "beta", "°": " deg", "≥": ">=", "≤": "<=", "−": "-", "±": "+-",
}  # fmt: skip


def provenance(doc: Mapping[str, Any], source: str) -> str:
    """Where the filter came from, in lines (for the exported files' header comment)."""
    tuned = f"tuned by {doc.get('tuned_method', '?')} (seed {doc.get('tuned_seed', '?')}"
    if isinstance(doc.get("tuned_cost"), (int, float)):
        tuned += f", cost {doc['tuned_cost']:.6g}"
    return "\n".join(
        [
            f"kftune filter: {doc['filter'].upper()} on model {doc['model']!r}, {tuned})",
            f"on dataset {doc['dataset']!r} ({doc['dataset_manoeuvres']} manoeuvres, "
            f"{doc['dataset_samples']} samples, sha256 {doc['dataset_sha256']}),",
            f"exported from {source} by {doc['exported_with']} (tuned with {doc['tuned_with']}).",
            "Q and R are diagonal; Q is the process-noise variance per step of dt."
            + (
                " Calibrated: run with Q and R as they are and multiply every covariance the"
                " filter reports (P, and S for the NIS) by covariance_scale ="
                f" {doc['covariance_scale']!r}; running with scaled Q and R instead moves a"
                " UKF's estimate."
                if "covariance_scale" in doc
                else ""
            ),
            *(
                [
                    "Model parameters tuned with the noise (the values below are the tuned "
                    "ones): "
                    + ", ".join(
                        f"{n} (recorded {v:.6g})"
                        for n, v in zip(
                            doc["tuned_model_param_names"], doc["tuned_model_param_starts"]
                        )
                    )
                    + "."
                ]
                if "tuned_model_param_names" in doc
                else []
            ),
            f"Initial state: {doc['initial_state']}",
        ]
    )


def to_c_header(doc: Mapping[str, Any], source: str, guard: str = "KFTUNE_FILTER_H") -> str:
    """A C header of macros only (:func:`c_macros`) with an include guard and the provenance
    in the opening comment. ``kftune export --format c`` writes these macros into its
    ``kftune_filter.h`` (:mod:`kftune.report.c_export`), beside the filter that runs.

    Raises:
        DataError: as :func:`c_macros`.
    """
    out = ["/*"]
    out += [f" * {_c_comment(line)}".rstrip() for line in provenance(doc, source).splitlines()]
    out += [" */", f"#ifndef {guard}", f"#define {guard}", ""]
    out += [c_macros(doc, source), f"#endif /* {guard} */", ""]
    return "\n".join(out)


def c_macros(doc: Mapping[str, Any], source: str) -> str:
    """The tuned values as C macros: ``#define`` scalars, and each array as an initialiser
    (``KFTUNE_Q_DIAG_INIT``, for ``static const double q[] = KFTUNE_Q_DIAG_INIT;``) and a
    C99 compound literal of it (``KFTUNE_Q_DIAG[i]``); units in comments. Macros, not
    ``static const`` arrays: a translation unit that uses some of the arrays compiles
    without unused-variable warnings (``-Wunused-const-variable=2 -Werror``).

    Raises:
        DataError: naming ``source``, when two names of one kind (states, inputs,
            measurements, model parameters) become the same macro (C names are upper
            case, with ``_`` for other characters: ``vx`` and ``VX``, ``a-b`` and ``a_b``).
    """
    p = "KFTUNE_"
    out: list[str] = []
    n, m = len(doc["states"]), len(doc["measurements"])
    out += [
        f"#define {p}N_STATES {n}",
        f"#define {p}N_INPUTS {len(doc['inputs'])}",
        f"#define {p}N_MEASUREMENTS {m}",
        f"#define {p}N_MODEL_PARAMS {len(doc['model_params'])}",
        f"#define {p}DT {_float(doc['dt'])} /* sample time [s] */",
        "",
    ]
    for what, names, units in (
        ("STATE", doc["states"], doc["state_units"]),
        ("INPUT", doc["inputs"], doc["input_units"]),
        ("MEASUREMENT", doc["measurements"], doc["measurement_units"]),
        ("MODEL_PARAM", doc["model_param_names"], doc["model_param_units"]),
    ):
        macros: dict[str, str] = {}
        for i, (name, unit) in enumerate(zip(names, units)):
            macro = f"{p}{what}_{_c_name(name)}"
            if macro in macros:
                kind = what.lower().replace("_", " ")
                raise DataError(
                    f"no C header: the {kind} names {macros[macro]!r} and {name!r} both "
                    f"become the macro {macro} (C names are upper case, with '_' for other "
                    "characters); rename one in the model, or export another --format",
                    file=source,
                )
            macros[macro] = name
            out.append(f"#define {macro} {i} /* {_c_comment(name)} [{unit}] */")
        out.append("")

    def array(name: str, values: list[float], labels: list[str], what: str) -> None:
        if not values:  # ISO C has no zero-size array: N_<name> = 0 says there is none
            out.extend([f"/* {what}: none */", ""])
            return
        out.append(f"/* {what} */")
        out.append(f"#define {p}{name}_INIT {{ \\")
        for v, label in zip(values, labels):
            out.append(f"    {_float(v)}, /* {_c_comment(label)} */ \\")
        out.append("}")
        out.extend([f"#define {p}{name} ((const double[{len(values)}]){p}{name}_INIT)", ""])

    array(
        "Q_DIAG",
        doc["q_diag"],
        [f"{s} [{u}]" for s, u in zip(doc["states"], doc["q_units"])],
        "process-noise variances per step of KFTUNE_DT, diagonal of Q, in state order",
    )
    array(
        "R_DIAG",
        doc["r_diag"],
        [f"{s} [{u}]" for s, u in zip(doc["measurements"], doc["r_units"])],
        "measurement-noise variances, diagonal of R, in measurement order",
    )
    if "covariance_scale" in doc:
        out.append(
            f"#define {p}COVARIANCE_SCALE {_float(doc['covariance_scale'])} "
            "/* multiply the reported P and S by it (calibration); Q and R run as they are */"
        )
        out.append("")
    array(
        "MODEL_PARAMS",
        doc["model_params"],
        [f"{s} [{u}]" for s, u in zip(doc["model_param_names"], doc["model_param_units"])],
        f"parameter vector p of model {doc['model']!r}",
    )
    if "ukf_alpha" in doc:
        out.append(f"/* sigma points: {_c_comment(doc['sigma_points'])} */")
        for key in ("alpha", "beta", "kappa"):
            out.append(f"#define {p}UKF_{key.upper()} {_float(doc[f'ukf_{key}'])}")
        out.append("")
    if "vehicle_name" in doc:
        out.append(f"/* vehicle: {_c_comment(doc['vehicle_name'])} */")
    for key, value in doc.items():
        if key.startswith("vehicle_") and key != "vehicle_name" and value is not None:
            name = key.removeprefix("vehicle_")
            unit = VEHICLE_UNITS.get(name, "")
            unit = _c_comment(unit)
            out.append(f"#define {p}VEHICLE_{_c_name(name)} {_float(value)} /* [{unit}] */")
    out.append("")
    return "\n".join(out)


# -- MATLAB --------------------------------------------------------------------------------


def _m_value(v: Any) -> str:
    if v is None:
        return "[]"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return _float(v) if isinstance(v, float) else str(v)
    return "'" + str(v).replace("'", "''") + "'"


def _m_list(values: list[Any]) -> str:
    if values and all(isinstance(v, str) for v in values):
        return "{" + ", ".join(_m_value(v) for v in values) + "}"
    return "[" + "; ".join(_m_value(v) for v in values) + "]"


def to_matlab(doc: Mapping[str, Any], source: str, var: str = "kf") -> str:
    """A MATLAB/Octave script that builds the struct ``var``: names as cell arrays, numbers
    as column vectors, ``Q`` and ``R`` as diagonal matrices, units in comments."""
    out = [f"% {line}".rstrip() for line in provenance(doc, source).splitlines()]
    out.append(f"{var} = struct();")
    comments = {
        "dt": "sample time [s]",
        "q_diag": "per step of dt: "
        + ", ".join(f"{s} [{u}]" for s, u in zip(doc["states"], doc["q_units"])),
        "r_diag": ", ".join(f"{s} [{u}]" for s, u in zip(doc["measurements"], doc["r_units"])),
        "covariance_scale": "multiply the reported P and S by it; Q and R run as they are",
        "model_params": ", ".join(
            f"{s} [{u}]" for s, u in zip(doc["model_param_names"], doc["model_param_units"])
        ),
    }
    for key, value in doc.items():
        if key.startswith("vehicle_") and key != "vehicle_name":
            name = key.removeprefix("vehicle_")
            unit = VEHICLE_UNITS.get(name, "")
            out.append(f"{var}.vehicle.{name} = {_m_value(value)}; % [{unit}]")
            continue
        if key == "vehicle_name":
            out.append(f"{var}.vehicle.name = {_m_value(value)};")
            continue
        text = _m_list(value) if isinstance(value, list) else _m_value(value)
        note = f" % {comments[key]}" if key in comments else ""
        out.append(f"{var}.{key} = {text};{note}")
    out.append(f"{var}.Q = diag({var}.q_diag);")
    out.append(f"{var}.R = diag({var}.r_diag);")
    return "\n".join(out) + "\n"


def render(doc: Mapping[str, Any], fmt: str, source: str, guard: str = "KFTUNE_FILTER_H") -> str:
    """The export in one of :data:`EXPORT_FORMATS`."""
    if fmt == "json":
        return to_json(doc)
    if fmt == "yaml":
        return to_yaml(doc, provenance(doc, source))
    if fmt == "c":
        return to_c_header(doc, source, guard)
    if fmt == "matlab":
        return to_matlab(doc, source)
    raise ValueError(f"format must be one of {list(EXPORT_FORMATS)}, got {fmt!r}")
