"""Depth priors by name: the built-in ones and any added with :func:`register_prior`.

The registry imports the prior modules, never the other way round, so that adding a
prior is one line here (or one ``register_prior`` call in user code) and no prior module
needs to know the registry exists.
"""

from __future__ import annotations

from typing import Callable

from .base import DepthPrior
from .fastdepth import FastDepthPrior
from .folder import FolderDepthPrior
from .hf import HFDepthPrior  # importing it does not import transformers
from .sensor import SensorDepthPrior

_REGISTRY: dict[str, Callable[..., DepthPrior]] = {
    "fastdepth": FastDepthPrior,
    "folder": FolderDepthPrior,
    "hf": HFDepthPrior,
    "sensor": SensorDepthPrior,
}


def register_prior(name: str):
    """Class/function decorator adding a factory under ``name`` (for priors outside recon)."""

    def add(factory):
        _REGISTRY[name] = factory
        return factory

    return add


def available_priors() -> tuple[str, ...]:
    return tuple(sorted(_REGISTRY))


def make_prior(name: str, **options) -> DepthPrior:
    """Build a prior by name: "fastdepth" (default), "folder", "sensor", "hf".

    ``options`` go to the prior's constructor, e.g. ``make_prior("folder", path="depth/",
    kind="disparity", align_to="fastdepth")``. A string ``align_to`` names another prior
    (built with the same device/batch/progress options).
    """
    if name not in _REGISTRY:
        raise ValueError(f"unknown depth prior {name!r}; choose one of {', '.join(sorted(_REGISTRY))}")
    align_to = options.get("align_to")
    if isinstance(align_to, str):
        shared = {k: options[k] for k in ("device", "batch_size", "progress") if k in options}
        options["align_to"] = make_prior(align_to, **shared)
    return _REGISTRY[name](**options)
