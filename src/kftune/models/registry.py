"""One registry of state-space models by name (the built-ins and the user's own)."""

from __future__ import annotations

from kftune.models.base import StateSpaceModel

__all__ = ["get_model", "model_names", "register_model", "resolve_model"]

_MODELS: dict[str, StateSpaceModel] = {}


def register_model(model: StateSpaceModel, *, replace: bool = False) -> StateSpaceModel:
    """Add ``model`` under ``model.name`` and return it.

    Raises:
        ValueError: not a StateSpaceModel, or the name is taken and ``replace`` is False.
    """
    if not isinstance(model, StateSpaceModel):
        raise ValueError(f"register_model needs a StateSpaceModel, got {type(model).__name__}")
    if model.name in _MODELS and not replace and _MODELS[model.name] is not model:
        raise ValueError(
            f"a model named {model.name!r} is already registered (pass replace=True to replace it)"
        )
    _MODELS[model.name] = model
    return model


def get_model(name: str) -> StateSpaceModel:
    """The registered model called ``name``.

    Raises:
        ValueError: no such model (the message lists the registered names).
    """
    try:
        return _MODELS[name]
    except (KeyError, TypeError):
        raise ValueError(
            f"unknown model {name!r}; registered models: {', '.join(model_names())}"
        ) from None


def model_names() -> list[str]:
    """Names of the registered models, sorted."""
    return sorted(_MODELS)


def resolve_model(model: StateSpaceModel | str) -> StateSpaceModel:
    """``model`` itself, or the registered model of that name."""
    return model if isinstance(model, StateSpaceModel) else get_model(model)
