"""The named choices of the configs and the command line, each defined once.

The configs check against these (``PipelineConfig.validate``, ``DemoOptions``,
``recon.poses.estimate_poses``) and the CLI offers them (argparse ``choices=``), so a
choice added here reaches both. No imports: building the CLI's parser stays cheap.
"""

from __future__ import annotations

# Where poses come from (PipelineConfig.poses, besides a pose file or folder; DemoOptions.poses):
# "auto" is the dataset's ground truth when it has one (the demo: estimate when the estimator
# is installed), else an estimate.
POSE_CHOICES = ("auto", "gt", "estimate")
# The pose estimator (PipelineConfig.pose_method, recon.poses.estimate_poses): "auto" runs the
# front end and falls back to SfM when tracking is lost.
POSE_METHODS = ("auto", "frontend", "sfm")
# The depth prior of `recon run` (PipelineConfig.prior): a network, a dataset's sensor depth,
# a folder of depth maps, a local Hugging Face depth model (recon.priors.hf).
PRIOR_CHOICES = ("fastdepth", "sensor", "folder", "hf")
# The metric depth an "hf" model's affine-invariant disparity is fitted to, frame by frame
# (PipelineConfig.prior_align; recon.priors.base.DepthPrior align_to): FastDepth on the same
# frames, or an RGB-D dataset's sensor depth.
PRIOR_ALIGN_CHOICES = ("fastdepth", "sensor")
# The prior of `recon demo` (DemoOptions.prior): ground truth distorted like a network, or the network.
DEMO_PRIORS = ("simulated", "fastdepth")
# The refinement after MEDeA (PipelineConfig.refine, recon.core.refine).
REFINE_CHOICES = ("mvs", "none")
# Rerun logging (PipelineConfig.rerun, --rerun). The same as viewer.rerun_log.MODES, restated
# so that the parser does not import the rerun SDK (a second, at every `recon --help`).
RERUN_MODES = ("spawn", "save", "serve", "off")

# What an estimated trajectory whose scale breaks becomes (PipelineConfig.on_break, --on-break):
# separate reconstructions, one per stretch; a stop naming the frames; one trajectory, warned.
ON_BREAK_CHOICES = ("segments", "stop", "keep")

# Streaming (PipelineConfig.stream, recon.drivers.streamed): auto streams inputs the frame budget cannot hold
# and videos whose poses are estimated (recon.pipeline.stream_reason).
STREAM_CHOICES = ("auto", "on", "off")

# Where the torch stages run (--device): "auto" is CUDA when there is one, else the CPU.
DEVICE_PATTERN = r"auto|cpu|cuda(?::(\d+))?"
DEVICE_SPELLINGS = "cpu, cuda, cuda:N or auto"

__all__ = ["DEMO_PRIORS", "DEVICE_PATTERN", "DEVICE_SPELLINGS", "ON_BREAK_CHOICES", "POSE_CHOICES", "POSE_METHODS",
           "PRIOR_ALIGN_CHOICES", "PRIOR_CHOICES", "REFINE_CHOICES", "RERUN_MODES", "STREAM_CHOICES"]
