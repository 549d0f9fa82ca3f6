"""State-space models: the model type, a registry, Jacobians and the built-in models.

Built-ins (registered on import): ``single-track`` (the paper's sideslip model),
``single-track-ay-bias`` and ``single-track-biases`` (with sensor-bias states) and ``ctrv``
(target tracking, no vehicle). :func:`linear_model` builds linear-Gaussian models.
"""

from kftune.models.base import (
    FIRST_MODEL_STOP,
    STOP_NONE,
    STOP_NUMERICAL,
    DataRefused,
    ModelKernels,
    StateSpaceModel,
    prepare_inputs,
)
from kftune.models.jacobians import FD_REL_STEP, measurement_jacobian, process_jacobian
from kftune.models.linear import linear_model, linear_params
from kftune.models.registry import get_model, model_names, register_model, resolve_model
from kftune.models.sideslip import SINGLE_TRACK, SINGLE_TRACK_AY_BIAS, SINGLE_TRACK_BIASES
from kftune.models.tracking import CTRV

for _model in (SINGLE_TRACK, SINGLE_TRACK_AY_BIAS, SINGLE_TRACK_BIASES, CTRV):
    register_model(_model)
del _model

__all__ = [
    "CTRV",
    "FD_REL_STEP",
    "FIRST_MODEL_STOP",
    "SINGLE_TRACK",
    "SINGLE_TRACK_AY_BIAS",
    "SINGLE_TRACK_BIASES",
    "STOP_NONE",
    "STOP_NUMERICAL",
    "DataRefused",
    "ModelKernels",
    "StateSpaceModel",
    "get_model",
    "linear_model",
    "linear_params",
    "measurement_jacobian",
    "model_names",
    "prepare_inputs",
    "process_jacobian",
    "register_model",
    "resolve_model",
]
