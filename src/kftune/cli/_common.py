"""Options shared by ``tune``, ``evaluate`` and ``compare``, and the TOML configuration.

A configuration file holds the same settings as the command line; an option given on the
command line wins over the file, the file over the defaults. One file can serve every
command: a key that only another command uses (marked below) is checked, then left out; an
unknown key is an error, not silently ignored::

    dataset = "default"            # or a dataset directory (relative to this file)
    method = "trbo"                # tune only (the paper's: "tsbo-tsp")
    budget = 40                    # tune only
    timeout = 30.0                 # tune only: per-evaluation limit [s], at most 1e6
    widen_bounds = false           # tune only: see kftune tune --widen-bounds
    calibration = "crps"           # tune only: the covariance scale's criterion, or "none"
                                   #   (= --no-calibration; see kftune tune --calibration)
    methods = ["manual", "ga", "tsbo-gp", "tsbo-tsp", "trbo"]   # compare only
    budgets = { ga = 225, tsbo-tsp = 40 }               # compare only
    seed = 0
    model = "single-track"         # a built-in model, or your own: "my_model.py[:NAME]"
    filter = "ukf"                 # or "ekf"
    r0 = { b_ay = 0.01 }           # R0 of measurements the dataset has no estimate for
    workers = 1                    # processes per cost evaluation (with scheduler = "local":
                                   #   the local Dask cluster's worker processes)
    scheduler = "tcp://host:8786"  # tune only: evaluate on a Dask cluster ("local": start one)
    batch = 4                      # tune only: points per batch (default: the Dask workers)
    burn_in = 0.0                  # [s] left out of cost and KPIs at each manoeuvre's start

    [cost]
    kind = "nrmse"                 # or "nlpd" / "crps" (rewards a calibrated σ); "pem" /
                                   #   "nis" / "msp": no reference sensor needed
    weights = { beta = 5.0, r = 1.0, ay = 1.0 }
    estimate = "posterior"         # or "prior" (see kftune.tuning.cost.CostSpec)
    normalise = "manoeuvre"        # or "dataset" (see kftune tune --help)

    [parameters]
    q_bounds = [1e-10, 1.0]        # or one box per parameter: { q_vy = [1e-8, 1e-2] }
    tune_r = "none"                # or "scale" (= tune_r_scale) or "diag": R's diagonal
    tune_r_scale = false
    tune_sigma_points = false
    tune_model = { C_af = [20000.0, 400000.0], C_ar = [20000.0, 400000.0] }
                                   # model parameters tuned with the noise (tune, compare)
    model_scale = { mu = "linear" }  # default log10 for a positive box, else linear

    [ukf]                          # sigma points when they are not tuned
    alpha = 1.0
    beta = 2.0
    kappa = 0.0

    [options.tsbo-tsp]             # passed to that optimiser, e.g. TSBO's max_fe
    max_fe = 15
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

from kftune.errors import ConfigError, DataError, UsageError, excerpt
from kftune.optim import (
    BATCH_RULE,
    MAX_BUDGET,
    MAX_TIMEOUT,
    METHODS,
    PeerUnavailableError,
    make_optimizer,
)
from kftune.settings import (
    NUMBER,
    Layer,
    Rule,
    SettingError,
    check,
    each,
    given,
    merge,
    rule,
    rules,
    setting,
    validate,
)
from kftune.tuning.calibrate import CRITERIA
from kftune.tuning.cost import CHANNELS, COST_KINDS, NORMALISATIONS
from kftune.tuning.parameterization import R_MODES

if TYPE_CHECKING:  # the filter and data layers load numba/scipy: only when a command runs
    from kftune.filters import UKFSettings
    from kftune.tuning.cost import CostSpec
    from kftune.tuning.parameterization import NoiseParameterization

#: Most worker processes (``--workers``): four per CPU of this machine. More only share the
#: same CPUs, each holding its own copy of the data (``--workers 100000`` would start a
#: hundred thousand processes).
MAX_WORKERS = 4 * (os.cpu_count() or 1)

#: Values of ``calibration`` (``tune --calibration``): a criterion of
#: :data:`kftune.tuning.calibrate.CRITERIA`, or "none" (no calibration).
CALIBRATIONS: tuple[str, ...] = (*CRITERIA, "none")
#: Most cost evaluations a method's budget may be (``budget``, ``budgets``, ``-n``).
_BUDGET: dict[str, Any] = {"kind": int, "low": 1, "high": MAX_BUDGET}


def _box(value: list[Any]) -> list[float]:
    """``[low, high]``: two numbers (a setting's converter; ValueError otherwise)."""
    if len(value) != 2 or not all(
        isinstance(v, (int, float)) and not isinstance(v, bool) for v in value
    ):
        raise ValueError("not [low, high]")
    return [float(v) for v in value]


def _boxes(value: list[Any] | dict[str, Any]) -> Any:
    """``q_bounds``: one ``[low, high]`` for all, or a table of one per parameter."""
    return _box(value) if isinstance(value, list) else {k: _box(v) for k, v in value.items()}


#: A tuned model parameter's box; the example is the single-track front cornering
#: stiffness's plausible range [N/rad] (the model, and so the parameter's own range, is not
#: known when the configuration is read: the run checks the box against it).
_BOX = each(
    list, convert=_box, what="[low, high] in the parameter's unit, e.g. C_af = [20000.0, 400000.0]"
)


@dataclass(frozen=True)
class CostTable:
    """``[cost]``: the cost (:class:`~kftune.tuning.cost.CostSpec`); None: not given."""

    kind: str | None = setting(kind=str, choices=COST_KINDS)
    weights: dict[str, float] | None = field(
        default=None, metadata=rule(dict, each=each(NUMBER, low=0))
    )
    estimate: str | None = setting(kind=str, choices=("posterior", "prior"))
    normalise: str | None = setting(kind=str, choices=NORMALISATIONS)


@dataclass(frozen=True)
class ParametersTable:
    """``[parameters]``: what is tuned (:class:`~kftune.tuning.parameterization.
    NoiseParameterization`); None: not given."""

    q_bounds: list[float] | dict[str, list[float]] | None = field(
        default=None,
        metadata=rule(
            (list, dict), convert=_boxes, what="[low, high] or a table { NAME = [low, high] }"
        ),
    )
    tune_r: str | None = setting(kind=str, choices=R_MODES)
    tune_r_scale: bool | None = setting(kind=bool)
    tune_sigma_points: bool | None = setting(kind=bool)
    r_scale_bounds: list[float] | None = field(
        default=None, metadata=rule(list, convert=_box, what="[low, high]")
    )
    tune_model: dict[str, list[float]] | None = field(default=None, metadata=rule(dict, each=_BOX))
    model_scale: dict[str, str] | None = field(
        default=None, metadata=rule(dict, each=each(str, choices=("log10", "linear")))
    )


@dataclass(frozen=True)
class UKFTable:
    """``[ukf]``: the sigma-point parameters where they are not tuned."""

    alpha: float | None = setting(kind=NUMBER, low=0, strict=True)
    beta: float | None = setting(kind=NUMBER, low=0)
    kappa: float | None = setting(kind=NUMBER)  # n + kappa > 0: checked for the model's n


@dataclass(frozen=True)
class RunConfig:
    """A configuration file (see the module docstring); None: not given, so that the
    command line, a tuned file or the default decides (:func:`pick`)."""

    dataset: str | None = setting(kind=str)
    method: str | None = setting(kind=str, choices=METHODS)
    methods: list[str] | None = field(
        default=None, metadata=rule(list, each=each(str, choices=METHODS))
    )
    budget: int | None = setting(**_BUDGET)
    budgets: dict[str, int] | None = field(
        default=None, metadata=rule(dict, keys=METHODS, each=each(**_BUDGET))
    )
    seed: int | None = setting(kind=int, low=0)
    model: str | None = setting(kind=str)
    filter: str | None = setting(kind=str, choices=("ukf", "ekf"))
    r0: dict[str, float] | None = field(
        default=None, metadata=rule(dict, each=each(NUMBER, low=0, strict=True))
    )
    workers: int | None = setting(kind=int, low=1, high=MAX_WORKERS)
    timeout: float | None = setting(kind=NUMBER, low=0, strict=True, high=MAX_TIMEOUT, unit="s")
    widen_bounds: bool | None = setting(kind=bool)
    calibration: str | None = setting(kind=str, choices=CALIBRATIONS)
    scheduler: str | None = setting(kind=str)
    batch: int | None = field(default=None, metadata={"rule": BATCH_RULE})
    burn_in: float | None = setting(kind=NUMBER, low=0, unit="s")
    cost: CostTable | None = field(default=None, metadata=rule(CostTable))
    parameters: ParametersTable | None = field(default=None, metadata=rule(ParametersTable))
    ukf: UKFTable | None = field(default=None, metadata=rule(UKFTable))
    options: dict[str, dict[str, Any]] | None = field(
        default=None, metadata=rule(dict, keys=METHODS, each=each(dict))
    )


#: Keys that only some commands use (the others check them, then leave them out).
USED_ONLY_BY: dict[str, set[str]] = {
    "method": {"tune"},
    "budget": {"tune"},
    "timeout": {"tune"},
    "widen_bounds": {"tune"},
    "calibration": {"tune"},
    "scheduler": {"tune"},
    "batch": {"tune"},
    "methods": {"compare"},
    "budgets": {"compare"},
    "seed": {"tune", "compare"},
    "options": {"tune", "compare"},
}
#: Method options that hold points or names of the tuned space, checked by the run (the
#: space is not known when the configuration is read).
_POINT_OPTIONS: frozenset[tuple[str, str]] = frozenset(
    {("manual", "points"), ("trbo", "x0"), ("trbo", "design_params")}
)


def load_config(path: str | Path | None, command: str | None = None) -> dict[str, Any]:
    """Read a TOML configuration and check it against :class:`RunConfig`; ``None`` gives
    an empty one. The result holds the keys the file gives, as tables (values converted:
    ``[low, high]`` as floats).

    A relative ``dataset`` is resolved against the file's directory. With ``command``,
    keys that only another command uses (:data:`USED_ONLY_BY`) are checked like the others,
    then left out of the result, so that one file serves ``tune``, ``evaluate`` and
    ``compare``.

    Raises:
        ConfigError: unreadable file, bad TOML, unknown key, wrong type or out-of-range
            value; names the file and the key.
    """
    if path is None:
        return {}
    p = Path(path)
    from kftune.data.jsonfile import read_toml

    try:
        data = given(validate(RunConfig, read_toml(p)))
    except DataError as exc:  # a configuration's errors are ConfigErrors (also exit 3)
        raise ConfigError(f"configuration {exc}") from None
    except SettingError as exc:
        exc.where = _in_file(p, exc.key)
        raise ConfigError(str(exc)) from None
    for method, opts in data.get("options", {}).items():
        # names and values, on a one-parameter space, before anything runs (points — the
        # manual method's and TR-BO's start points — depend on the tuned space's
        # dimension: the run checks them)
        checkable = {k: v for k, v in opts.items() if (method, k) not in _POINT_OPTIONS}
        if method == "trbo" and "x0" in opts:
            checkable["x0"] = [0.5]  # a point of the check's space: options that need one
        try:
            make_optimizer(method, {"x": (0.0, 1.0)}, seed=0, **checkable)
        except PeerUnavailableError:
            pass  # the run itself says which package is missing
        except SettingError as exc:  # a value the method's settings record refuses
            exc.where = f"configuration file {p}, [options.{method}] key {excerpt(exc.key)}"
            raise ConfigError(str(exc)) from None
        except (ValueError, TypeError) as exc:
            raise ConfigError(f"configuration file {p}, [options.{method}]: {exc}") from None
    if "dataset" in data and data["dataset"] != "default":
        ds = Path(data["dataset"])
        data["dataset"] = str(ds if ds.is_absolute() else (p.parent / ds))
    if "model" in data:
        data["model"] = model_file_from(data["model"], p.parent)
    if command is not None:  # checked above; another command's settings
        for key, users in USED_ONLY_BY.items():
            if command not in users:
                data.pop(key, None)
    data[_FILE] = str(p)
    return data


def split_model_file(spec: str) -> tuple[Path, str] | None:
    """(file with ``~`` expanded, ":NAME" or "") of a model-file spec, read as the loader
    reads it (:func:`kftune.models.user.model_file_parts`); None for a model name."""
    from kftune.models.user import model_file_parts

    parts = model_file_parts(spec)
    if parts is None:
        return None
    return Path(parts[0]).expanduser(), ":" + parts[1] if parts[1] else ""


def model_file_from(spec: str, folder: Path) -> str:
    """``spec`` with a relative model-file path read relative to ``folder`` (where the
    configuration or tuned file that names it lies); a model name as it is."""
    mf = split_model_file(spec)
    if mf is None or mf[0].is_absolute():
        return spec
    return str(folder / mf[0]) + mf[1]


def model_file_for(spec: str, out: Path) -> str:
    """How a file written to ``out`` records the model ``spec`` so that
    :func:`model_file_from` finds it again from any working directory: a model file
    relative to ``out``'s folder when it lies below it (the pair can move together),
    otherwise absolute; a model name as it is."""
    mf = split_model_file(spec)
    if mf is None:
        return spec
    path, folder = mf[0].resolve(), out.parent.resolve()  # a link to the file: its folder
    return str(path.relative_to(folder) if path.is_relative_to(folder) else path) + mf[1]


#: Key under which :func:`load_config` records the file it read (for error messages).
_FILE = "_file"


def _in_file(file: str | Path, key: str) -> str:
    """``"configuration file run.toml, [cost] key 'weights.beta'"``: where a key of a
    configuration lies, for messages."""
    section, _, rest = key.partition(".")
    where = f"[{section}] key {excerpt(rest)}" if rest else f"key {excerpt(key)}"
    return f"configuration file {file}, {where}"


def _where(config: Mapping[str, Any], section: str) -> str:
    """``"run.toml [cost]"`` — where a section's values came from, for error messages."""
    return f"{config[_FILE]} [{section}]" if _FILE in config else f"[{section}]"


def layers(
    args: argparse.Namespace | None,
    config: Mapping[str, Any],
    tuned: tuple[str | Callable[[str], str], Mapping[str, Any]] | None = None,
    defaults: Mapping[str, Any] | None = None,
    section: str = "",
    options: Mapping[str, str] | None = None,
) -> list[Layer]:
    """The sources of settings in precedence order: the command line (``args``: a key's
    option is ``--key-name``, or ``options[key]``), the configuration file, a tuned file
    (``tuned``: (what it is called, or a function of the key saying where that key lies;
    its settings)) and the defaults; ``section``: the configuration's table (``"cost"``)
    that holds the keys."""
    table = config.get(section, {}) if section else config
    file = config.get(_FILE, "the configuration")
    inner = f"{section}." if section else ""
    opts = options or {}
    out = []
    if args is not None:
        names = vars(args)
        cli = {k: names.get(o.lstrip("-").replace("-", "_")) for k, o in opts.items()}
        given = {**names, **cli} if not section else cli
        out.append(
            Layer(
                {k: v for k, v in given.items() if v is not None},  # argparse's None: not given
                lambda k: opts.get(k, f"--{k.replace('_', '-')}"),
                "command line",
            )
        )
    out.append(Layer(table, lambda k: _in_file(file, inner + k), "file"))
    if tuned is not None:
        named = tuned[0]
        where = named if callable(named) else lambda k: str(named)
        out.append(Layer(tuned[1], where, "tuned"))
    fallback = {k: v for k, v in (defaults or {}).items() if v is not None}  # None: no default
    out.append(Layer(fallback, lambda k: f"the default {k}", "default"))
    return out


#: Each setting's value where neither the command line, the configuration file nor a tuned
#: file gives one: the last layer of the merge (:func:`pick`, :func:`model_choice`).
DEFAULTS: Final[Mapping[str, Any]] = {
    "seed": 0,
    "workers": 1,
    "burn_in": 0.0,
    "widen_bounds": False,
    "model": "single-track",
    "filter": "ukf",
}
_DEFAULT: Any = object()  # pick's default: that of DEFAULTS


def pick(
    args: argparse.Namespace, config: Mapping[str, Any], key: str, default: Any = _DEFAULT
) -> Any:
    """The command-line value if given, else the configuration's, else ``default`` (where
    not passed: :data:`DEFAULTS`' value of ``key``, or None); checked against the
    configuration's rule of ``key`` (:class:`RunConfig`), so that a bad value names its
    source."""
    fallback = DEFAULTS.get(key) if default is _DEFAULT else default
    chosen = merge({key: _RULES.get(key, _ANY)}, layers(args, config, defaults={key: fallback}))
    return chosen[key][0] if key in chosen else None


def pick_tuned(
    args: argparse.Namespace, config: Mapping[str, Any], key: str, tuned: tuple[Path, Any] | None
) -> Any:
    """:func:`pick` with a tuned file ``tuned`` (path, document) between the configuration
    and the defaults: the value the file was tuned with where neither the command line nor
    the configuration gives one (e.g. the burn-in it was scored with)."""
    was = None if tuned is None else (lambda k: f"tuned file {tuned[0]}, key {k!r}", tuned[1])
    found = layers(args, config, was, defaults={key: DEFAULTS.get(key)})
    chosen = merge({key: _RULES.get(key, _ANY)}, found)
    return chosen[key][0] if key in chosen else None


def budgets(
    args_budgets: list[tuple[str, int]] | None, config: Mapping[str, Any]
) -> dict[str, int]:
    """The evaluations per method (``compare``): ``--budget METHOD=N`` over the
    configuration's ``budgets`` table, method by method, each checked by the rule of a
    budget (:func:`merge`; a bad one names the option or the file and key)."""
    file = config.get(_FILE, "the configuration")
    found = [
        Layer(dict(args_budgets or []), lambda m: f"--budget {m}=…", "command line"),
        Layer(config.get("budgets", {}), lambda m: _in_file(file, f"budgets.{m}"), "file"),
    ]
    chosen = merge(dict.fromkeys(METHODS, _RULES["budget"]), found)
    return {m: v for m, (v, _) in chosen.items()}


#: A rule that takes any value: for settings checked where they are read.
_ANY = Rule((object,))


def add_command(subparsers: Any, name: str, help: str, doc: str | None) -> argparse.ArgumentParser:
    """A subcommand parser whose ``--help`` shows the module docstring (as plain text)."""
    return subparsers.add_parser(
        name,
        help=help,
        description=(doc or "").replace("``", ""),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )


def _plain(text: str) -> bool:
    """Not the digit separators and non-ASCII digits that int() and float() accept ("2_2.5"
    would read as 22.5); :mod:`kftune.data.textfile` refuses them in files."""
    return "_" not in text and text.isascii()


def arg_type(r: Rule) -> Callable[[str], Any]:
    """An argparse type: a number that ``r`` accepts (the configuration's rule of the same
    setting), else an error that says what ``r`` expects (exit code 2)."""
    kind = int if r.kind == (int,) else float

    def parse(text: str) -> Any:
        try:
            return check(r, kind(text) if _plain(text) else None, "")
        except (ValueError, SettingError):
            raise argparse.ArgumentTypeError(
                f"expected {r.describe()}, got {excerpt(text)}"
            ) from None

    return parse


_RULES = rules(RunConfig)
BUDGET = arg_type(_RULES["budget"])
BATCH = arg_type(BATCH_RULE)  # the rule Execution checks
WORKERS = arg_type(_RULES["workers"])
NON_NEGATIVE_INT = arg_type(_RULES["seed"])
NON_NEGATIVE_FLOAT = arg_type(_RULES["burn_in"])
TIMEOUT_SECONDS = arg_type(_RULES["timeout"])


def add_common(parser: argparse.ArgumentParser, *, tuning: bool = True) -> None:
    """Dataset, ``--config``, workers, cost options, ``--json``; with ``tuning`` also the
    seed, the parameterisation flags and ``--quiet``."""
    parser.add_argument(
        "dataset",
        nargs="?",
        default=None,
        help="dataset: 'default' (the bundled one, the default), a kftune dataset "
        "directory or manifest, or a directory in the revs-250lm layout",
    )
    parser.add_argument("--config", type=Path, help="TOML file with these settings")
    parser.add_argument(
        "--model",
        metavar="NAME|FILE.py[:VAR]",
        help="the filter's state-space model: a built-in one (default single-track, the "
        "paper's; see 'kftune models') or a Python file defining your own. A model file is "
        "Python code that runs with your rights: name only files you trust (kftune never "
        "runs one because a tuned file names it)",
    )
    parser.add_argument(
        "--filter", choices=("ukf", "ekf"), help="unscented (default) or extended Kalman filter"
    )
    if tuning:
        parser.add_argument(
            "--seed", type=NON_NEGATIVE_INT, help="seed driving all randomness (default 0)"
        )
    parser.add_argument(
        "--workers",
        type=WORKERS,
        help="processes that run the manoeuvres of one cost evaluation in parallel (default "
        f"1; at most {MAX_WORKERS}, four per CPU of this machine: more only share the CPUs)",
    )
    cost = parser.add_argument_group("cost")
    cost.add_argument(
        "--cost",
        choices=COST_KINDS,
        help="nrmse: the paper's weighted NRMSE (default; tune without any cost option or "
        "[cost] key: --normalise dataset with R's diagonal tuned, unless --tune-r-scale, "
        "tune_r or tune_r_scale says otherwise; --cost nrmse gives the paper's cost with Q "
        "alone; README 'Which cost'); nlpd / crps: the negative log density / CRPS of the "
        "reference under the filter's Gaussian (estimate ± σ), which reward an accurate and "
        "calibrated σ (default weights beta=1); "
        "pem: the innovation likelihood (prediction-error method), msp: multi-step "
        "prediction error (single-track UKF) and nis: NIS consistency, all three without a "
        "reference sensor",
    )
    cost.add_argument(
        "--weights",
        type=_weights_arg,
        metavar="CH=W,...",
        help=f"nrmse, nlpd, crps weights per channel (default beta=5,r=1,ay=1; nlpd and crps: "
        "beta=1, reference channels only): a measurement of the model "
        f"(single-track: {list(CHANNELS[1:])}), scored against its data channel, or an "
        "output or unmeasured state (single-track: beta, vy), scored against the data's "
        "reference channel <name>_ref",
    )
    cost.add_argument(
        "--estimate",
        choices=("posterior", "prior"),
        help="score yaw rate, ay and Vx with the posterior h(x+) (default, the paper) or the "
        "one-step prediction, which cannot copy the measurement",
    )
    cost.add_argument(
        "--normalise",
        choices=NORMALISATIONS,
        help="nrmse: divide each manoeuvre's RMSE by its own max|X| (manoeuvre, default, the "
        "paper's Eq. 15) or the RMSE over all manoeuvres by their largest |X| (dataset: the "
        "error in the channel's unit; tune's default, with R's diagonal, where no cost "
        "option is given; README 'Which cost')",
    )
    cost.add_argument(
        "--burn-in",
        type=NON_NEGATIVE_FLOAT,
        metavar="SECONDS",
        help="leave each manoeuvre's first SECONDS out of cost and KPIs (default 0)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    if not tuning:
        return
    parser.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    par = parser.add_argument_group("tuned parameters")
    par.add_argument(
        "--tune-r-scale",
        action="store_true",
        default=None,
        help="also tune a scale factor of R",
    )
    par.add_argument(
        "--tune-sigma-points",
        action="store_true",
        default=None,
        help="also tune the sigma-point parameters alpha, beta, kappa",
    )
    par.add_argument(
        "--tune-model",
        type=tune_model_arg,
        action="append",
        metavar="NAME=LOW:HIGH[:SCALE]",
        help="also tune a parameter of the model (repeatable; 'kftune models' lists them, "
        "e.g. C_af=20000:400000 or mu=0.4:1.6:linear), starting from its recorded value; "
        "SCALE log10 (default for LOW > 0: stiffness, mass and friction are uncertain by a "
        "factor) or linear; wins over the configuration's tune_model for that name",
    )


def tune_model_arg(text: str) -> tuple[str, float, float, str | None]:
    """``"C_af=20000:400000"`` or ``"mu=0.4:1.6:linear"`` → (name, low, high, scale or
    None) (errors say what was expected; argparse adds the option's name)."""
    name, sep, box = text.partition("=")
    parts = box.split(":")
    if not sep or not name.strip() or len(parts) not in (2, 3):
        raise argparse.ArgumentTypeError(
            f"expected NAME=LOW:HIGH or NAME=LOW:HIGH:SCALE (e.g. C_af=20000:400000), got {text!r}"
        )
    values = []
    for part in parts[:2]:
        try:
            v = float(part) if _plain(part) else math.nan
        except ValueError:
            v = math.nan
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(
                f"{name.strip()}: bounds must be finite numbers, got {part!r} in {text!r}"
            )
        values.append(v)
    scale = parts[2] if len(parts) == 3 else None
    if scale is not None and scale not in ("log10", "linear"):
        raise argparse.ArgumentTypeError(
            f"{name.strip()}: scale must be log10 or linear, got {scale!r}"
        )
    return name.strip(), values[0], values[1], scale


def parse_weights(text: str) -> dict[str, float]:
    """``"beta=5,r=1,ay=1"`` → dict (errors name the bad item; argparse adds the option's
    name)."""
    out: dict[str, float] = {}
    for item in text.split(","):
        name, sep, value = item.partition("=")
        name = name.strip()
        try:
            w = float(value) if _plain(value) else math.nan
        except ValueError:
            w = math.nan
        if not sep or not name or not math.isfinite(w):
            raise ConfigError(f"expected CHANNEL=NUMBER items, e.g. beta=5,r=1,ay=1, got {item!r}")
        out[name] = w
    return out


def _weights_arg(text: str) -> dict[str, float]:
    try:
        return parse_weights(text)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


#: What ``kftune tune`` tunes where neither the command line nor the configuration says
#: anything of the cost or R: the NRMSE divided per channel by its largest |X| over the
#: training set (``normalise = "dataset"``) with R's diagonal tuned beside Q, the setting
#: that was as accurate or better on held-out manoeuvres of four of five datasets (at
#: most 0.9 % worse on the fifth) with calibrated coverage as good (BENCHMARKS.md,
#: "kftune's recommended setting"). ``compare`` (the paper's reproduction) and
#: ``evaluate --manual`` keep the paper's Eq. 15 with Q alone.
RECOMMENDED_NORMALISE: Final = "dataset"
RECOMMENDED_TUNE_R = "diag"


def recommended(args: argparse.Namespace, config: dict[str, Any]) -> bool:
    """Whether ``kftune tune``'s recommended setting applies: the command is tune and no
    option or ``[cost]`` key of :data:`_COST_OPTIONS` is given, any one of which makes
    tune's cost the user's, on the paper's defaults (Eq. 15, Q alone) as before."""
    if getattr(args, "command", None) != "tune":
        return False
    section = config.get("cost", {})
    return not any(getattr(args, o[2:], None) or k in section for k, o in _COST_OPTIONS.items())


def cost_spec(
    args: argparse.Namespace,
    config: dict[str, Any],
    tuned: dict[str, Any] | None = None,
    model: Any = None,
    tuned_file: str | Path | None = None,
) -> CostSpec:
    """The cost from the command line and configuration; ``tuned``: a tuned file's cost
    (``tuned_file``: that file, named where one of its values is bad, e.g. a null),
    whose settings stand where neither gives one (and none of which carries over to
    another kind of cost); ``model`` (a StateSpaceModel): the channels weighed must be
    ones it can score, or the error names where the weights came from."""
    spec, chosen = _cost_spec(args, config, tuned, tuned_file)
    if recommended(args, config):
        spec = dataclasses.replace(spec, normalise=RECOMMENDED_NORMALISE)
    if model is not None:
        from kftune.tuning.runs import check_cost_channels

        try:
            check_cost_channels(spec, model)
        except ConfigError as exc:
            if "weights" in chosen and chosen["weights"][1].name != "tuned":
                raise _refused(chosen["weights"][1], "weights", str(exc)) from None
            raise
    return spec


#: The costs that weigh channels (``--weights``, ``[cost] weights``): the NRMSE, the scoring
#: rules and the multi-step prediction (its channels); nis and pem take none.
WEIGHTED_COSTS = "nrmse, nlpd, crps and msp"
#: The cost's settings, each with its command-line option.
_COST_OPTIONS = {
    "kind": "--cost",
    "weights": "--weights",
    "estimate": "--estimate",
    "normalise": "--normalise",
}


def _refused(layer: Layer, key: str, problem: str) -> ConfigError:
    """The error of a setting ``key`` that ``layer`` gave: a usage error (exit 2) for the
    command line, else a configuration error (exit 3), naming where it lies."""
    error = UsageError if layer.name == "command line" else ConfigError
    return error(f"{layer.where(key)}: {problem}")


def _cost_spec(
    args: argparse.Namespace,
    config: dict[str, Any],
    tuned: dict[str, Any] | None,
    tuned_file: str | Path | None = None,
) -> tuple[CostSpec, dict[str, tuple[Any, Layer]]]:
    """The cost, and where each of its settings came from (:func:`merge`: command line,
    ``[cost]``, the tuned file's cost ``tuned`` when of the same kind)."""
    from kftune.tuning.cost import CostSpec

    base = dict(tuned or {})
    tuned_with = "the cost the parameters were tuned with"
    in_file = f"{tuned_file}, " if tuned_file is not None else ""

    def chosen_from(base: Mapping[str, Any]) -> dict[str, tuple[Any, Layer]]:
        was = (lambda k: f"{tuned_with} ({in_file}key 'cost_spec.{k}')", base)
        found = layers(args, config, was, section="cost", options=_COST_OPTIONS)
        return merge(dict.fromkeys(_COST_OPTIONS, _ANY), found)

    chosen = chosen_from(base)
    kind = chosen["kind"][0] if "kind" in chosen else CostSpec().kind
    if kind != base.get("kind", CostSpec().kind):
        chosen = chosen_from({})  # no setting of another kind of cost carries over
    by = chosen["kind"][1] if "kind" in chosen else None
    if by is None:  # where the kind came from, for messages
        source = "the default"
    elif by.name == "command line":
        source = f"--cost {kind}"
    elif by.name == "tuned":
        source = tuned_with
    else:
        source = by.where("kind") + f" = {kind!r}"
    mine = {k: layer for k, (_, layer) in chosen.items() if layer.name != "tuned"}
    if kind in ("nis", "pem") and "weights" in mine:  # they would be ignored: say so
        raise _refused(
            mine["weights"],
            "weights",
            f"the {kind} cost ({source}) weighs no channels: weights apply to the "
            f"{WEIGHTED_COSTS} costs; leave them out or use one of those",
        )
    if kind != "nrmse" and "normalise" in mine:  # only the NRMSE is normalised: say so
        raise _refused(
            mine["normalise"],
            "normalise",
            f"the {kind} cost ({source}) is not an NRMSE: normalise applies to the nrmse cost "
            "only; leave it out or use nrmse",
        )
    try:
        return CostSpec(**{k: v for k, (v, _) in chosen.items()}), chosen
    except ConfigError as exc:  # e.g. no weight > 0
        layer = chosen["weights"][1] if "weights" in chosen else chosen["kind"][1]
        raise _refused(layer, "weights" if "weights" in chosen else "kind", str(exc)) from None


def burn_in(args: argparse.Namespace, config: dict[str, Any]) -> float:
    """The burn-in [s] from the command line and configuration."""
    return float(pick(args, config, "burn_in"))


def model_choice(
    args: argparse.Namespace, config: dict[str, Any], tuned: Mapping[str, Any] | None = None
) -> tuple[str, str]:
    """(model spec, filter name) from the command line, else the configuration (a model file
    named there is relative to that file), else the tuned file ``tuned`` (the model it was
    tuned with), else the paper's single-track UKF."""
    chosen = _model_layers(args, config, None if tuned is None else ("", tuned))
    return chosen["model"][0], chosen["filter"][0]


def _model_layers(
    args: argparse.Namespace,
    config: Mapping[str, Any],
    tuned: tuple[str | Callable[[str], str], Mapping[str, Any]] | None,
) -> dict[str, tuple[Any, Layer]]:
    """The model and filter, each with the layer that gave it (:func:`merge`)."""
    keys = dict.fromkeys(("model", "filter"), _ANY)  # what they name: filter_spec checks
    try:
        return merge(keys, layers(args, config, tuned, DEFAULTS))
    except SettingError as exc:  # a tuned file's null
        raise ConfigError(str(exc)) from None


def filter_spec_of(
    args: argparse.Namespace,
    config: dict[str, Any],
    vehicle: Any,
    tuned: tuple[Path, Mapping[str, Any]] | None = None,
    dataset: str | None = None,
) -> Any:
    """The :class:`~kftune.tuning.runs.FilterSpec` of :func:`model_choice` (loads a model
    file). An unusable model or filter says where that setting was named: an unknown
    ``--model`` name or ``--filter`` is a usage error (exit 2); a model file, the
    configuration or the tuned file ``tuned`` (path, document) bad input (exit 3). A model
    the data do not fit (a vehicle model on the dataset ``dataset`` (its name) without a
    vehicle) blames no setting: it names the dataset (exit 3)."""
    from kftune.errors import ModelChoiceError
    from kftune.tuning.runs import filter_spec

    path = None if tuned is None else tuned[0]
    was = None if tuned is None else (lambda k: f"{path}: the {k} it was tuned with", tuned[1])
    chosen = _model_layers(args, config, was)
    model, filt = chosen["model"][0], chosen["filter"][0]
    try:
        return filter_spec(model, filt, vehicle)
    except ModelChoiceError as exc:
        if exc.key is None:  # the data lack what the model needs: no setting is wrong
            if dataset is None:
                raise
            raise ModelChoiceError(f"dataset {dataset!r}: {exc}", None) from None
        layer = chosen[exc.key][1]
        if layer.name == "default":
            raise
        named = exc.key == "filter" or split_model_file(model) is None  # not a model file
        usage = layer.name == "command line" and named
        error = UsageError if usage else ConfigError
        raise error(f"{layer.where(exc.key)}: {exc}") from None


def parameterization(
    args: argparse.Namespace, config: dict[str, Any], model: Any = None
) -> NoiseParameterization:
    """What is tuned, from the command line and configuration, for ``model`` (a
    StateSpaceModel; None: the single-track model)."""
    from kftune.tuning.parameterization import NoiseParameterization

    section = config.get("parameters", {})
    kwargs: dict[str, Any] = {
        "tune_r_scale": bool(pick(args, section, "tune_r_scale", False)),
        "tune_sigma_points": bool(pick(args, section, "tune_sigma_points", False)),
        "default_settings": _ukf_settings(config, 3 if model is None else model.n_states),
    }
    if "tune_r" in section:
        kwargs["tune_r"] = section["tune_r"]
    elif recommended(args, config) and pick(args, section, "tune_r_scale", None) is None:
        kwargs["tune_r"] = RECOMMENDED_TUNE_R  # unless R's tuning is given either way

    for key in ("q_bounds", "r_scale_bounds"):  # [low, high], or one per parameter
        if key in section:
            b = section[key]
            kwargs[key] = {n: tuple(v) for n, v in b.items()} if isinstance(b, dict) else tuple(b)
    if model is not None:
        kwargs.update(states=model.state_names, measurements=model.measurement_names)
    given = _model_boxes(args, config, section)
    if given:
        kwargs["model_bounds"] = {n: (lo, hi) for n, (lo, hi, _, _) in given.items()}
        kwargs["model_scales"] = {n: sc for n, (_, _, sc, _) in given.items() if sc}
    try:
        p = NoiseParameterization(**kwargs)
        p.space  # noqa: B018 — validates the bounds
    except ValueError as exc:
        where = next((g[3] for n, g in given.items() if repr(n) in str(exc)), None)
        if where is not None and where.startswith("--"):
            raise UsageError(f"{where}: {exc}") from None
        raise ConfigError(f"{_where(config, 'parameters')}: {exc}") from None
    if p.model_names:
        from kftune.models import SINGLE_TRACK
        from kftune.tuning.parameterization import check_model_params

        for name, (lo, hi, _, origin) in given.items():
            one = NoiseParameterization(model_bounds={name: (lo, hi)})
            try:
                check_model_params(one, model if model is not None else SINGLE_TRACK)
            except ConfigError as exc:
                if origin.startswith("--"):
                    raise UsageError(f"{origin}: {exc}") from None
                raise ConfigError(f"{_where(config, 'parameters')}: {exc}") from None
    return p


def _model_boxes(
    args: argparse.Namespace, config: dict[str, Any], section: Mapping[str, Any]
) -> dict[str, tuple[float, float, str | None, str]]:
    """Tuned model parameters, name → (low, high, scale or None, where it was given): the
    configuration's ``tune_model``/``model_scale``, then ``--tune-model`` (which wins for
    its names; without a scale it keeps the configuration's ``model_scale`` of the name;
    a name given twice on the command line is refused, naming it)."""
    where = _where(config, "parameters")
    out: dict[str, tuple[float, float, str | None, str]] = {}
    scales = section.get("model_scale", {})
    for name in scales:
        if name not in section.get("tune_model", {}):
            raise ConfigError(
                f"{where}: model_scale names {name!r}, which tune_model does not tune "
                f"(tuned: {sorted(section.get('tune_model', {}))})"
            )
    for name, (low, high) in section.get("tune_model", {}).items():
        out[name] = (float(low), float(high), scales.get(name), f"tune_model.{name}")
    named: set[str] = set()
    for name, low, high, scale in getattr(args, "tune_model", None) or []:
        if name in named:
            raise UsageError(f"--tune-model {name} is given twice; give each parameter once")
        named.add(name)
        out[name] = (low, high, scale or scales.get(name), f"--tune-model {name}")
    return out


def _ukf_settings(config: dict[str, Any], n: int = 3) -> UKFSettings:
    """The ``[ukf]`` sigma-point parameters (ranges checked by :class:`UKFTable`) for an
    ``n``-state filter, whose ``kappa`` must keep n + κ > 0 (Julier and Uhlmann 1997)."""
    from kftune.filters import UKFSettings

    table = config.get("ukf", {})
    s = UKFSettings(**{k: float(v) for k, v in table.items()})
    if not n + s.kappa > 0:
        where = _in_file(config.get(_FILE, "the configuration"), "ukf.kappa")
        raise ConfigError(
            f"{where}: expected a number > {-n} (n + kappa > 0 for the {n}-state filter), "
            f"got {excerpt(table.get('kappa'))}"
        )
    return s


def emit_json(obj: Any) -> None:
    """Print one strict-JSON object on stdout."""
    print(json.dumps(obj, allow_nan=False, indent=1))
