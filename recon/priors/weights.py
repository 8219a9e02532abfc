"""Where model weights come from.

Weights are never shipped in (or copied into) the repository. A model named ``name`` is
looked for as ``<place>/<name>/<filename>`` in this order:

1. an explicit path given by the caller (CLI ``--weights``): either the file itself, the
   model's folder, or a folder holding ``<name>/``;
2. ``$RECON_WEIGHTS`` (same three forms);
3. ``../shared/weights`` next to the repository checkout;
4. ``~/.cache/recon/weights``.

Nothing is ever downloaded.
"""

from __future__ import annotations

import os
from pathlib import Path

from ..errors import ReconInputError

ENV_VAR = "RECON_WEIGHTS"
# parents[2] is the repository checkout (recon/priors/weights.py -> repo); its sibling
# ``shared/`` is where the project keeps data and weights that are not ours to commit.
SHARED_WEIGHTS = Path(__file__).resolve().parents[2].parent / "shared" / "weights"
CACHE_WEIGHTS = Path("~/.cache/recon/weights")


def weight_roots(explicit: str | os.PathLike | None = None) -> list[Path]:
    """The places searched, most specific first (explicit path, env var, shared, cache)."""
    roots = []
    if explicit is not None:
        roots.append(Path(explicit).expanduser())
    env = os.environ.get(ENV_VAR)
    if env:
        roots.append(Path(env).expanduser())
    roots.append(SHARED_WEIGHTS)
    roots.append(CACHE_WEIGHTS.expanduser())
    return roots


def _candidates(root: Path, name: str, filename: str) -> list[Path]:
    """A root may be the file, the model folder, or a folder holding ``name/``."""
    if root.is_file():
        return [root]
    return [root / name / filename, root / filename]


def find_weights(name: str, filename: str, explicit: str | os.PathLike | None = None) -> Path:
    """Path of ``filename`` of model ``name``.

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
    tried = []
    for root in weight_roots():
        for path in _candidates(root, name, filename):
            tried.append(path)
            if path.is_file():
                return path
    raise ReconInputError(
        f"{name} weights not found (tried: {', '.join(map(str, tried))}); "
        f"pass --weights or set ${ENV_VAR} to the folder holding {name}/{filename}"
    )
