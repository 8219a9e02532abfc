"""Where model weights come from.

The default FastDepth weights (Wofk et al., ICRA 2019; MIT licence) ship with the package as
``recon/priors/models/<name>.npz`` (format: :mod:`recon.priors.packaged`), the only weights
in the repository. A model named ``name`` is looked for in an explicit path (CLI
``--weights``: the file, the model's folder, or a folder holding ``<name>/`` or
``<name>.npz``), then ``$RECON_WEIGHTS`` (same forms), then the packaged file. An explicit
path that holds nothing is an error; ``$RECON_WEIGHTS`` that holds nothing falls through.
Nothing is ever downloaded. More: docs/depth.md#the-packaged-model-file
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import ReconInputError

ENV_VAR = "RECON_WEIGHTS"
# Package data (pyproject.toml [tool.setuptools.package-data]), so a plain `pip install .`
# has it too.
PACKAGED_MODELS = Path(__file__).resolve().parent / "models"
PACKAGED_SUFFIX = ".npz"


def packaged_weights(name: str) -> Path:
    """Where the packaged file of model ``name`` lies (whether or not it exists)."""
    return PACKAGED_MODELS / f"{name}{PACKAGED_SUFFIX}"


def weight_roots(explicit: str | os.PathLike | None = None) -> list[Path]:
    """The places searched, most specific first (explicit path, env var, packaged models)."""
    roots = []
    if explicit is not None:
        roots.append(Path(explicit).expanduser())
    env = os.environ.get(ENV_VAR)
    if env:
        roots.append(Path(env).expanduser())
    roots.append(PACKAGED_MODELS)
    return roots


def _candidates(root: Path, name: str, filename: str) -> list[Path]:
    """A root may be the file, the model folder, or a folder holding ``name/`` or ``name.npz``."""
    if root.is_file():
        return [root]
    return [root / name / filename, root / filename, root / f"{name}{PACKAGED_SUFFIX}"]


def find_weights(name: str, filename: str, explicit: str | os.PathLike | None = None) -> Path:
    """Path of the weights of model ``name``: its TF.js ``filename`` or its packaged ``.npz``.

    An explicit path that holds no such file is an error even when another place would
    have one: the user asked for that path.

    Raises:
        ReconInputError: one line listing every place tried.
    """
    if explicit is not None:
        tried = _candidates(Path(explicit).expanduser(), name, filename)
        for path in tried:
            if path.is_file():
                return path
        raise ReconInputError(
            f"{name} weights not found at --weights {explicit} (tried: {', '.join(map(str, tried))})"
        )
    # weight_roots() is the one statement of the order; the packaged folder holds only <name>.npz.
    tried = [path for root in weight_roots()
             for path in ([packaged_weights(name)] if root == PACKAGED_MODELS else _candidates(root, name, filename))]
    for path in tried:
        if path.is_file():
            return path
    raise ReconInputError(
        f"{name} weights not found (tried: {', '.join(map(str, tried))}); the packaged file is missing from"
        f" this install: reinstall recon, or pass --weights or set ${ENV_VAR} to the folder holding {name}/{filename}"
    )
