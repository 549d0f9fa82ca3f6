"""``kftune models``: the state-space models a filter can run, or one model in detail.

Lists the built-in models (and, with ``--model FILE.py``, your own): their states, inputs,
measurements and outputs with units, which are the data channels a filter reads by name and
the ``q_<state>`` parameters ``tune`` searches, the model's parameters with their
plausible ranges (what ``tune --tune-model NAME=LOW:HIGH`` can search with the noise), and
the channels a dataset needs for them: t, the inputs and measurements by name, and
``<output>_ref`` for a cost on an output.
"""

from __future__ import annotations

import argparse
from typing import Any

from kftune.cli._common import add_command, emit_json
from kftune.cli.exit_codes import EXIT_OK


def register(subparsers: Any) -> None:
    """Add ``models``."""
    p = add_command(subparsers, "models", "list the state-space models a filter can run", __doc__)
    p.add_argument(
        "--model",
        metavar="NAME|FILE.py[:VAR]",
        help="describe this model only (a built-in one or a Python file defining your own)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def describe(model: Any) -> dict[str, Any]:
    """A model's names and units as JSON-ready data, and the data channels it needs."""
    from kftune.tuning.runs import output_names

    def pairs(names: tuple[str, ...], units: tuple[str, ...]) -> list[dict[str, str]]:
        return [{"name": n, "unit": u} for n, u in zip(names, units)]

    return {
        "name": model.name,
        "description": model.description,
        "states": pairs(model.state_names, model.state_units),
        "inputs": pairs(model.input_names, model.input_units),
        "measurements": pairs(model.measurement_names, model.measurement_units),
        "outputs": list(output_names(model)),
        "parameters": [
            {
                "name": n,
                "unit": u,
                "default": v,
                "range": list(model.param_ranges[n]) if n in model.param_ranges else None,
            }
            for n, u, v in zip(model.param_names, model.param_units, model.param_defaults)
        ],
        "jacobians": "analytic" if model.F is not None and model.H is not None else "numerical",
        "data": {
            "channels": ["t", *model.input_names, *model.measurement_names],
            "references": [f"{o}_ref" for o in output_names(model)],
            "vehicle": bool(model.needs_vehicle),
        },
    }


def run(args: argparse.Namespace) -> int:
    """Run ``kftune models``."""
    from kftune.models import get_model, model_names
    from kftune.models.user import load_model

    models = [load_model(args.model)] if args.model else [get_model(n) for n in model_names()]
    docs = [describe(m) for m in models]
    if args.json:
        emit_json({"models": docs})
        return EXIT_OK
    for d in docs:
        print(f"{d['name']}: {d['description']}")
        for key in ("states", "inputs", "measurements"):
            cells = ", ".join(f"{c['name']} [{c['unit']}]" for c in d[key]) or "none"
            print(f"  {key:13s} {cells}")
        print(f"  {'outputs':13s} {', '.join(d['outputs']) or 'none'}")
        cells = ", ".join(
            f"{c['name']} [{c['unit']}]"
            + (f" {c['range'][0]:g}…{c['range'][1]:g}" if c["range"] is not None else "")
            for c in d["parameters"]
        )
        print(f"  {'parameters':13s} {cells or 'none'}")
        print(f"  {'EKF Jacobians':13s} {d['jacobians']}")
        data = d["data"]
        refs = ", ".join(data["references"])
        print(
            f"  {'data':13s} channels {', '.join(data['channels'])}"
            + (f"; for a cost on an output its reference ({refs})" if refs else "")
            + ("; a vehicle" if data["vehicle"] else "")
        )
    return EXIT_OK
