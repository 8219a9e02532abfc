"""Local Hugging Face depth models (DPT, Depth Anything, ZoeDepth, GLPN, ...) as priors.

Optional extra: ``transformers`` is imported only when an HF prior is built. Models are
loaded from a local folder with ``local_files_only=True``; nothing is downloaded.
Whether the output is metric depth or affine-invariant disparity is read from the model
config (:func:`model_kind`) and reported in ``PriorOutput.kind``.
"""

from __future__ import annotations

import contextlib
import importlib.util
import inspect
from pathlib import Path

import numpy as np
import torch

from ..errors import ReconInputError
from .base import PRIOR_KINDS, DepthPrior, PriorOutput
from .resample import resize_bilinear

# Architectures whose depth head is trained for metric depth in metres.
METRIC_MODEL_TYPES = ("zoedepth", "glpn", "depth_pro")


_MISSING_TRANSFORMERS = ("the 'hf' depth prior needs the optional dependency transformers: pip install 'recon[hf]'"
                         " (or pip install transformers)")


def _transformers():
    try:
        import transformers
    except ImportError:
        raise ReconInputError(_MISSING_TRANSFORMERS) from None
    return transformers


def check_model_folder(model) -> Path:
    """The cheap checks of an HF prior, without importing transformers or reading weights:
    ``model`` is a folder holding config.json, and transformers is installed. Returns the
    path; raises ReconInputError (one line) otherwise. Whether transformers can load the
    model is known only by loading it (:class:`HFDepthPrior`)."""
    path = Path(model).expanduser()
    if not path.exists():
        raise ReconInputError(f"{path}: no such Hugging Face model folder (models are never downloaded)")
    if not path.is_dir():
        raise ReconInputError(f"{path}: not a folder; a local Hugging Face model is a folder with config.json")
    if not (path / "config.json").is_file():
        raise ReconInputError(
            f"{path}: not a local Hugging Face model folder (no config.json); models are never downloaded"
        )
    if importlib.util.find_spec("transformers") is None:
        raise ReconInputError(_MISSING_TRANSFORMERS)
    return path


@contextlib.contextmanager
def _quiet_loading(transformers, progress: bool):
    """transformers' own output while loading: its load report (a multi-line table, on
    stderr) is not shown, its weight-loading bar only with ``progress``."""
    logging = transformers.utils.logging
    verbosity, bar = logging.get_verbosity(), logging.is_progress_bar_enabled()
    logging.set_verbosity_error()
    if not progress:
        logging.disable_progress_bar()
    try:
        yield
    finally:
        logging.set_verbosity(verbosity)
        if bar:
            logging.enable_progress_bar()


def _load_error(exc: Exception) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if "ignore_mismatched_sizes" in text:  # transformers points at the report it printed; we did not print it
        text = "its weights do not have the sizes config.json gives"
    return text


def model_kind(config) -> str:
    """"metric" or "affine_disparity" from a transformers model config.

    Depth Anything states it (``depth_estimation_type`` "metric"/"relative"); ZoeDepth, GLPN
    and Depth Pro are metric; DPT/MiDaS and relative Depth Anything predict affine-invariant
    inverse depth.
    """
    stated = getattr(config, "depth_estimation_type", None)
    if stated is not None:
        return "metric" if stated == "metric" else "affine_disparity"
    return "metric" if getattr(config, "model_type", "") in METRIC_MODEL_TYPES else "affine_disparity"


class HFDepthPrior(DepthPrior):
    """Depth from a local transformers ``AutoModelForDepthEstimation`` checkpoint.

    Args:
        model: folder holding config.json, the weights and preprocessor_config.json
            (what ``save_pretrained`` writes for the model and its image processor).
        kind: override the output kind from :func:`model_kind` (e.g. "up_to_scale").
        batch_size, device, progress, align_to: see DepthPrior (``align_to`` turns
            affine-invariant disparity into metric depth).
    """

    name = "hf"

    def __init__(self, model, kind: str | None = None, batch_size: int = 4, device: str = "cpu",
                 progress: bool = True, align_to=None):
        super().__init__(batch_size=batch_size, device=device, progress=progress, align_to=align_to)
        self.path = check_model_folder(model)
        transformers = _transformers()
        try:
            with _quiet_loading(transformers, progress):
                self.processor = transformers.AutoImageProcessor.from_pretrained(self.path, local_files_only=True)
                self.model = transformers.AutoModelForDepthEstimation.from_pretrained(self.path,
                                                                                      local_files_only=True)
        except Exception as exc:  # anything in a folder the user gave: bad JSON, weights, sizes, model type
            raise ReconInputError(f"{self.path}: cannot load the depth model ({_load_error(exc)})") from None
        self.model = self.model.eval().to(device)
        self.kind = kind or model_kind(self.model.config)
        if self.kind not in PRIOR_KINDS:
            raise ValueError(f"kind must be one of {PRIOR_KINDS}, got {kind!r}")

    @torch.inference_mode()
    def predict_batch(self, frames, intrinsics, indices, plan=None) -> PriorOutput:
        size = tuple(frames.shape[1:3])
        inputs = self.processor(images=list(frames), return_tensors="pt")
        inputs = {k: v.to(self.device) for k, v in inputs.items() if isinstance(v, torch.Tensor)}
        outputs = self.model(**inputs)
        post = getattr(self.processor, "post_process_depth_estimation", None)
        if post is not None:
            # The processor knows its own padding/cropping (e.g. ZoeDepth pads) and undoes it.
            sizes = {"target_sizes": [size] * len(frames)}
            if "source_sizes" in inspect.signature(post).parameters:
                sizes["source_sizes"] = [size] * len(frames)
            maps = torch.stack([r["predicted_depth"] for r in post(outputs, **sizes)])
        else:
            maps = resize_bilinear(outputs.predicted_depth, size)
        maps = maps.float().cpu().numpy()
        valid = np.isfinite(maps) & (maps > 0)
        depth = np.where(valid, maps, 0.0).astype(np.float32)
        return PriorOutput(depth=depth, kind=self.kind,
                           info={"model": "hf", "path": str(self.path),
                                 "model_type": getattr(self.model.config, "model_type", None),
                                 "output": self.kind})
