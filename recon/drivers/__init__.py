"""The two drivers of a run, side by side: :mod:`recon.drivers.oneshot` holds every frame at
once; :mod:`recon.drivers.streamed` (with its passes ``stream_track`` and ``stream_depth`` and
the window plan ``stream_plan``) keeps memory flat on long videos. Both run the same stages
(:mod:`recon.core.stages`); :mod:`recon.pipeline` chooses which one runs. What they share
is here once: ``result`` (RunResult, what a run returns), ``recording`` (the Rerun recording
opened) and ``segments`` (a trajectory whose scale breaks)."""
