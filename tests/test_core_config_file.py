"""`recon run --config FILE` (recon.core.config_file): report.json's options reproduce a run's
config exactly, YAML sections per stage, flags over the file, bad files in one line; and the
command line's defaults are the config's."""

import json
from pathlib import Path

import pytest

from recon.commands.cli import main
from recon.commands.cli_args import build_parser
from recon.commands.cli_config import pipeline_config_from_args
from recon.core.config import PipelineConfig

RICH = ["--stride", "2", "--max-frames", "40", "--stream", "off", "--fov", "62.5", "--distortion", "0.1,-0.02,0,0",
        "--poses", "given.txt", "--pose-option", "window=6", "--prior", "sensor", "--preset", "paper",
        "--stage1-epochs", "30", "--refine-option", "num_sources=3", "--voxel-size", "0.01", "--max-triangles", "5000",
        "--no-npy", "--on-break", "stop", "--quiet"]


def _config(*argv: str) -> PipelineConfig:
    parser = build_parser()
    return pipeline_config_from_args(parser.parse_args(["run", *argv]), parser)


@pytest.fixture(autouse=True)
def _plain_machine(monkeypatch):
    """--device auto and the Rerun default depend on the machine: pin them to a CPU box
    without a display, so that the comparisons mean the same everywhere."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr("recon.commands.cli_config.default_rerun_mode", lambda: "off")


def test_cli_defaults_are_the_configs():
    """A bare `recon run IN -o OUT` is PipelineConfig(IN, OUT): field for field, sections too."""
    assert _config("in.mp4", "-o", "out").to_dict() == PipelineConfig(Path("in.mp4"), Path("out")).to_dict()


def test_report_options_reproduce_the_config(tmp_path):
    """report.json's options (to_dict), fed back with --config, give the same config, and a
    whole report.json works the same."""
    original = _config("in.mp4", "-o", str(tmp_path / "a"), *RICH)
    options = original.to_dict()
    (tmp_path / "options.json").write_text(json.dumps(options))
    (tmp_path / "report.json").write_text(json.dumps({"input": {"path": "in.mp4"}, "options": options}))
    for name in ("options.json", "report.json"):
        again = _config("in.mp4", "-o", str(tmp_path / "a"), "--config", str(tmp_path / name))
        assert again.to_dict() == options
        assert again == original  # typed alike: tuples, paths, nested configs


def test_yaml_sections_and_flags_over_the_file(tmp_path):
    path = tmp_path / "run.yaml"
    path.write_text("stride: 3\nrefine: none\nfov: 70\nmedea:\n  pixel_stride: 4\n  stage1:\n    epochs: 12\n"
                    "fusion:\n  max_triangles: 20000\n  voxel_size: 0.02\n")
    config = _config("in.mp4", "-o", "out", "--config", str(path), "--voxel-size", "0.005")
    assert config.stride == 3 and config.refine == "none" and config.fov == 70.0
    assert config.medea.pixel_stride == 4 and config.medea.stage1.epochs == 12
    assert config.medea.stage2.epochs == PipelineConfig(Path("i"), Path("o")).medea.stage2.epochs  # kept
    assert config.fusion.max_triangles == 20000 and config.fusion.voxel_size == 0.005  # the flag wins
    assert config.input == Path("in.mp4") and config.output == Path("out")


@pytest.mark.parametrize("content, expected", [
    ("strde: 3\n", "unknown setting(s) strde"),
    ("fusion:\n  voxel: 0.01\n", "config fusion: unknown setting(s) voxel"),
    ("- 1\n- 2\n", "a config file holds a mapping of settings, got list"),
    ("stride: [1\n", "not a YAML config"),
])
def test_bad_config_files_are_one_line(tmp_path, capsys, content, expected):
    path = tmp_path / "bad.yaml"
    path.write_text(content)
    _fails_in_one_line(tmp_path, capsys, expected, "--config", str(path))
    assert not (tmp_path / "out").exists()


def test_set_types_each_setting_like_its_field_and_wins_over_flags_and_file(tmp_path):
    path = tmp_path / "run.yaml"
    path.write_text("fusion:\n  voxel_size: 0.02\n")
    config = _config("in.mp4", "-o", "out", "--config", str(path), "--voxel-size", "0.005",
                     "--set", "fusion.voxel_size=0.03", "--set", "medea.stage1.epochs=7", "--set", "fov=none",
                     "--set", "intrinsics=500,510,320,240", "--set", "polish=yes", "--set", "weights=/tmp/w",
                     "--set", "medea.feature_loss=M", "--set", 'pose_options={"window": 6}')
    assert config.fusion.voxel_size == 0.03 and config.medea.stage1.epochs == 7 and config.fov is None
    assert config.intrinsics == (500.0, 510.0, 320.0, 240.0) and config.polish is True
    assert config.weights == Path("/tmp/w") and config.medea.feature_loss == "M"
    assert config.pose_options == {"window": 6}


@pytest.mark.parametrize("item, expected", [
    ("medea.stage1.epoch=3", "--set medea.stage1.epoch: no such setting (did you mean medea.stage1.epochs,"),
    ("frame_budget=lots", "--set frame_budget: 'lots' is not a valid int"),
    ("medea.feature_loss=X", "--set medea.feature_loss: 'X' is not a valid"),
    ("stride", "--set must be KEY=VALUE"),
])
def test_bad_settings_are_one_line(tmp_path, capsys, item, expected):
    _fails_in_one_line(tmp_path, capsys, expected, "--set", item)


def _fails_in_one_line(tmp_path, capsys, expected: str, *options: str) -> None:
    """`recon run` with `options` stops with exit 2 and one `recon: error:` line holding `expected`."""
    code = main(["run", str(tmp_path / "missing.mp4"), "-o", str(tmp_path / "out"), *options])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("recon: error:") and expected in err[0], err


def test_set_list_names_every_setting_with_its_default(capsys):
    from recon.core.config_file import setting_types

    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["run", "--set", "list"])
    assert stop.value.code == 0
    listed = capsys.readouterr().out.splitlines()[1:]
    defaults = PipelineConfig(Path("IN"), Path("OUT"))
    assert [line.split()[0] for line in listed] == list(setting_types(defaults))
    assert "medea.stage1.epochs" in {line.split()[0] for line in listed}
    row = next(line.split() for line in listed if line.startswith("frame_budget "))
    assert row[-1] == str(defaults.frame_budget)


def test_the_command_line_of_a_config_makes_that_config(tmp_path):
    """recon.commands.cli_config.command_line (what `recon demo` prints) parsed again is the same config."""
    import shlex
    from dataclasses import replace

    from recon.commands.cli_config import command_line

    original = _config("in.mp4", "-o", str(tmp_path / "a"), *RICH)
    original = replace(original, pose_options={"window": 6, "keyframe_flow": 12.5}, overwrite=True,
                       intrinsics=(500.0, 510.0, 320.0, 240.0), prior_path=tmp_path / "prior dir")
    words = shlex.split(command_line(original, build_parser()))
    assert words[:2] == ["recon", "run"]
    assert _config(*words[2:]) == original


@pytest.mark.parametrize("name", ["fast", "paper"])
def test_presets_are_shipped_config_files(name, tmp_path):
    """--preset NAME reads recon/core/presets/NAME.yaml (a medea section, nothing else), which
    is medea_core's preset of that name; the same file works as --config."""
    from medea_core import MedeaConfig
    from recon.core.config_file import preset_path, read_config_file

    path = preset_path(name)
    assert set(read_config_file(path)) == {"medea"}
    expected = MedeaConfig.fast() if name == "fast" else MedeaConfig()
    assert _config("in.mp4", "-o", "out", "--preset", name).medea == expected
    assert _config("in.mp4", "-o", "out", "--config", str(path)).medea == expected
