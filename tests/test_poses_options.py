"""The pose settings documented and bounded on their fields (issue 65): every field of
FrontendConfig and SfMConfig has an attribute docstring, `--pose-option list` shows each
summary, and the ranges declared with ``bounded`` refuse what the checks refused before."""

import math
import re
from dataclasses import fields

import pytest

from recon.errors import ReconInputError
from recon.options import field_docs, field_summary
from recon.poses.config import FrontendConfig
from recon.poses.options import _option_fields, check_pose_config, check_pose_options, pose_option_table
from recon.poses.sfm.mapper import SfMConfig

CONFIGS = (FrontendConfig, SfMConfig)


@pytest.mark.parametrize("cls", CONFIGS)
def test_every_field_has_a_docstring_and_the_class_docstring_is_short(cls):
    docs = field_docs(cls)
    assert [f.name for f in fields(cls)] == list(docs)
    for name, doc in docs.items():
        summary = field_summary(cls, name)
        assert summary and summary[-1] in ".)", (name, summary)
        assert len(summary) <= 120, (name, len(summary))
        if doc.startswith("See "):  # a grouped entry points at its first field, which exists
            assert doc.split()[1].rstrip(":.") in docs, (name, doc)
    lines = cls.__doc__.strip().splitlines()
    assert 1 <= len(lines) <= 4, lines
    # The descriptions left the class docstring: no "name: ..." entry is left in it.
    assert not [n for n in docs if re.search(rf"^\s*{n}[:,]", cls.__doc__, re.MULTILINE)]


def _blocks(table: str) -> dict[str, str]:
    """{option: its summary lines joined} of pose_option_table's text."""
    blocks: dict[str, list[str]] = {}
    name = None
    for line in table.splitlines():
        if line.startswith(" "):
            blocks[name].append(line.strip())
        else:
            name = line.split()[0]
            blocks[name] = []
    return {k: " ".join(v) for k, v in blocks.items()}


def test_the_option_list_shows_each_summary_within_100_columns():
    table = pose_option_table()
    assert max(len(line) for line in table.splitlines()) <= 100
    blocks = _blocks(table)
    assert set(blocks) == set(_option_fields())
    for name, text in blocks.items():
        owners = [cls for cls in CONFIGS if name in cls.__dataclass_fields__]
        for cls in owners:
            assert field_summary(cls, name) in text, name
        if len(owners) == 2:  # calibrate_lens means a different thing in each: both, named
            assert text.startswith("FrontendConfig: ") and " SfMConfig: " in text


# The ranges the checks held as one table before they moved onto the fields: the same words.
BEFORE = {
    ">= 1": ("ba_stride", "temporal_radius", "window", "calib_stride", "calib_flow_stride", "calib_iters",
             "align_chunk", "torch_threads", "max_keyframes", "keyframe_stride", "max_num_features", "overlap",
             "num_threads", "loop_candidates"),
    ">= 0": ("proximity_edges", "proximity_nms", "final_proximity_edges", "window_iters", "global_iters",
             "prior_weight", "calibrate_after", "calibrate_iters", "max_lost", "reloc_candidates", "seed_min_flow"),
    "> 0": ("keyframe_flow", "keyframe_max_flow", "proximity_max_flow", "calib_tol", "keyframe_motion"),
    "in [0, 1]": ("proximity_min_overlap", "min_edge_weight", "lost_inlier", "min_registered"),
    "in [-1, 1]": ("min_match_correlation", "min_local_correlation"),
    ">= 2": ("calib_keyframes", "loop_words"),
    "two numbers >= 1": ("correction_grid",),
    "'incremental' or 'global'": ("mapper",),
    "'retrieval', 'exhaustive' or 'none'": ("loop_matching",),
}


def _declared() -> dict[str, str]:
    return {f.name: f.metadata["bounds"].words for cls in CONFIGS for f in fields(cls) if "bounds" in f.metadata}


def test_the_ranges_on_the_fields_are_the_table_they_replace():
    assert _declared() == {name: words for words, names in BEFORE.items() for name in names}
    check_pose_config(FrontendConfig())  # every default lies in its range
    check_pose_config(SfMConfig())


def _outside(words: str):
    """A value a setting bounded by `words` refuses (just past the bound where there is one)."""
    return {">= 1": 0, ">= 0": -1, "> 0": 0.0, "in [0, 1]": 1.5, "in [-1, 1]": -1.01, ">= 2": 1,
            "two numbers >= 1": (0, 4)}.get(words, "bogus")


@pytest.mark.parametrize("name", sorted(_declared()))
def test_a_value_outside_a_fields_range_is_refused_with_its_words(name):
    words = _declared()[name]
    bad = _outside(words)
    message = re.escape(f"pose option {name} must be {words}, got {bad!r}")
    with pytest.raises(ReconInputError, match=message):
        check_pose_options({name: bad})
    owner = FrontendConfig if name in FrontendConfig.__dataclass_fields__ else SfMConfig
    with pytest.raises(ReconInputError, match=message):
        check_pose_config(owner(**{name: bad}))


def test_the_checks_keep_their_other_rules():
    """Settings without a range must be finite; None and booleans pass; the SfM's own front-end
    settings are checked too; nested configs are not settings of the command line."""
    with pytest.raises(ReconInputError, match=r"pose option lens_k1 must be finite, got nan"):
        check_pose_options({"lens_k1": math.nan})
    with pytest.raises(ReconInputError, match=r"pose option keyframe_flow must be > 0, got inf"):
        check_pose_options({"keyframe_flow": math.inf})
    check_pose_options({"torch_threads": None, "keyframe_stride": None, "calibrate_lens": True, "lens_k1": -0.2})
    with pytest.raises(ReconInputError, match=r"pose option window must be >= 1, got 0"):
        check_pose_config(SfMConfig(frontend=FrontendConfig(window=0)))
    with pytest.raises(ReconInputError, match="unknown pose option"):
        check_pose_options({"windw": 3})
    assert {"flow", "features", "ba", "normal_flow", "frontend"}.isdisjoint(_option_fields())
