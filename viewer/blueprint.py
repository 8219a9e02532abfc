"""The default Rerun layout (blueprint) sent with every recon recording.

Owns which views a recording opens on (rerun-sdk 0.41 ``rerun.blueprint``):
:class:`viewer.RerunLogger` sends it as the active and default blueprint in every mode
(spawn, save, serve), so a saved .rrd carries it. Tab "reconstruction": the 3D scene of
/world over a row of RGB, depths, confidence and the tracking log; tab "MEDeA losses": bar
charts of each term's loss per epoch (not time series: a view plots against the time
panel's timeline, which opens on "frame"). The time panel follows the newest frame.
More: docs/outputs.md#what-a-recording-holds
"""

from __future__ import annotations

from collections.abc import Sequence

import rerun as rr
import rerun.blueprint as rrb
from rerun.blueprint.encodings import TextLogColumn, TimelineColumn

from .entities import (
    ADJUSTED_DEPTH,
    CONFIDENCE,
    EPOCH_TIMELINE,
    FRAME_TIMELINE,
    LOSSES,
    PRIOR_DEPTH,
    REFINED_DEPTH,
    RGB,
    TIME_TIMELINE,
    TRACKING,
)

RECONSTRUCTION_TAB = "reconstruction"
LOSSES_TAB = "MEDeA losses"
SCENE_VIEW = "3D scene"
# Metres from the camera centre to the image in the 3D view: room scale (what recon mostly
# reconstructs); the view's selection panel changes it.
FRUSTUM_DEPTH = 0.3
# The stages medea_core.run_medea reports (MedeaResult.history keys).
LOSS_STAGES = ("stage1", "stage2")

# Depth and confidence share the camera's pinhole with the RGB: in 3D they would be
# back-projected on top of the mesh, so the 3D view leaves them to the 2D row.
_NOT_IN_3D = (PRIOR_DEPTH, ADJUSTED_DEPTH, REFINED_DEPTH, CONFIDENCE)
_IMAGES = (
    (RGB, "RGB"),
    (PRIOR_DEPTH, "prior depth"),
    (ADJUSTED_DEPTH, "MEDeA depth"),
    (REFINED_DEPTH, "refined depth"),
    (CONFIDENCE, "confidence"),
)
_DEPTHS = (PRIOR_DEPTH, ADJUSTED_DEPTH, REFINED_DEPTH)


def default_blueprint(loss_stages: Sequence[str] = LOSS_STAGES) -> rrb.Blueprint:
    """The layout every recording opens with (see the module docstring); pure, so tests
    can inspect it. loss_stages: one loss plot per MEDeA stage."""
    scene = rrb.Spatial3DView(
        name=SCENE_VIEW,
        origin="/world",
        contents=["+ /world/**", *(f"- /{entity}" for entity in _NOT_IN_3D)],
        # Rerun sizes the frustum to a small share of the scene, too small to see its RGB.
        defaults=[rr.Pinhole.from_fields(image_plane_distance=FRUSTUM_DEPTH)],
    )
    # Turbo like Rerun's 3D default, stated so that every depth panel uses the same map.
    depth_defaults = [rr.DepthImage.from_fields(colormap=rr.components.Colormap.Turbo)]
    row = rrb.Horizontal(
        *(rrb.Spatial2DView(name=name, origin=f"/{entity}", contents="$origin",
                            defaults=depth_defaults if entity in _DEPTHS else None)
          for entity, name in _IMAGES),
        # The state line names its frame: level and text only, so it fits a narrow column.
        rrb.TextLogView(
            name="tracking",
            origin=f"/{TRACKING}",
            columns=rrb.TextLogColumns(
                timeline_columns=[TimelineColumn(FRAME_TIMELINE, visible=False),
                                  TimelineColumn(TIME_TIMELINE, visible=False)],
                text_log_columns=[TextLogColumn("entitypath", visible=False), TextLogColumn("loglevel"),
                                  TextLogColumn("body")],
            ),
        ),
    )
    reconstruction = rrb.Vertical(scene, row, row_shares=[3, 1], name=RECONSTRUCTION_TAB)
    losses = rrb.Grid(
        *(rrb.BarChartView(name=f"MEDeA {stage}: loss per epoch", origin=f"/{LOSSES}/{stage}")
          for stage in loss_stages),
        name=LOSSES_TAB,
    )
    return rrb.Blueprint(
        rrb.Tabs(reconstruction, losses, active_tab=0),
        # "following" shows the newest frame: the whole reconstruction of a saved run, the
        # growing one of a live run.
        rrb.TimePanel(timeline=FRAME_TIMELINE, play_state="following", state="collapsed"),
        # Side panels folded away so that the scene gets the window; one click opens them.
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )


__all__ = ["default_blueprint", "FRAME_TIMELINE", "EPOCH_TIMELINE", "LOSS_STAGES", "LOSSES_TAB",
           "RECONSTRUCTION_TAB", "SCENE_VIEW"]
