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
        "--set", "medea.stage1.epochs=30", "--set", "mvs.num_sources=3", "--voxel-size", "0.01",
        "--max-triangles", "5000", "--no-npy", "--on-break", "stop", "--quiet"]


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
    """--preset NAME reads recon/core/presets/NAME.yaml (inherit: defaults, and a medea section), which
    is recon's MEDeA of that name (fast: the default, pipeline_medea; paper: MedeaConfig()); the same
    file works as --config."""
    import yaml

    from medea_core import MedeaConfig
    from recon.core.config import pipeline_medea
    from recon.core.config_file import preset_path

    path = preset_path(name)
    assert set(yaml.safe_load(path.read_text())) == {"inherit", "medea"}  # the rest: defaults.yaml's
    expected = pipeline_medea() if name == "fast" else MedeaConfig()
    assert _config("in.mp4", "-o", "out", "--preset", name).medea == expected
    assert _config("in.mp4", "-o", "out", "--config", str(path)).medea == expected
    # The other settings of the file are a bare run's: --config PRESET changes MEDeA only.
    bare = _config("in.mp4", "-o", "out", "--preset", name)
    assert _config("in.mp4", "-o", "out", "--config", str(path)) == bare


def test_defaults_yaml_is_written_from_the_dataclasses():
    """presets/defaults.yaml is what write_defaults writes now (a default or a field docstring
    changed without `python scripts/write_defaults.py` fails here), and read back it is
    PipelineConfig's defaults, every setting but the command line's own named."""
    import yaml

    from recon.core.config_file import DEFAULTS, NOT_IN_DEFAULTS, defaults_yaml, read_config_file, setting_types
    from recon.core.config_file import updated as with_file

    assert DEFAULTS.read_text() == defaults_yaml(), "run: python scripts/write_defaults.py"
    defaults = PipelineConfig(Path("IN"), Path("OUT"))
    assert with_file(defaults, read_config_file(DEFAULTS)) == defaults
    changed = with_file(defaults, {"medea": {"stage1": {"epochs": 3}}})
    assert with_file(changed, read_config_file(DEFAULTS)) == defaults  # every MEDeA setting is in it

    def names(values: dict, prefix: str = "") -> set[str]:
        return {n for k, v in values.items()
                for n in (names(v, f"{prefix}{k}.") if isinstance(v, dict) and k != "pose_options" else {prefix + k})}

    listed = {n for n in setting_types(defaults) if not NOT_IN_DEFAULTS & set(n.split("."))}
    assert names(yaml.safe_load(DEFAULTS.read_text())) == listed


def test_inherit_reads_the_named_file_first(tmp_path, capsys):
    """`inherit: PATH` (relative to the file) or a preset's name: the file's settings over the
    other's, section by section; a loop is one line."""
    (tmp_path / "base.yaml").write_text("stride: 3\nmedea:\n  pixel_stride: 4\n  stage1:\n    epochs: 12\n")
    (tmp_path / "run.yaml").write_text("inherit: base.yaml\nmedea:\n  stage1:\n    epochs: 20\n")
    config = _config("in.mp4", "-o", "out", "--config", str(tmp_path / "run.yaml"))
    assert config.stride == 3 and config.medea.pixel_stride == 4 and config.medea.stage1.epochs == 20
    (tmp_path / "paper.yaml").write_text("inherit: paper\nfov: 70\n")
    config = _config("in.mp4", "-o", "out", "--config", str(tmp_path / "paper.yaml"))
    assert config.fov == 70.0 and config.medea.stage1.epochs == 600
    (tmp_path / "loop.yaml").write_text("inherit: loop.yaml\n")
    _fails_in_one_line(tmp_path, capsys, "inherits from itself", "--config", str(tmp_path / "loop.yaml"))


def test_every_setting_has_one_description():
    """Each setting --set reaches is documented by its field's docstring (recon.options.field_docs),
    the text `recon run --help` and defaults.yaml are made from."""
    from dataclasses import fields, is_dataclass

    from recon.options import field_docs

    def undocumented(config, prefix: str = "") -> list[str]:
        docs = field_docs(type(config))
        missing = [prefix + f.name for f in fields(config) if not docs.get(f.name, "").strip()]
        for f in fields(config):
            if is_dataclass(getattr(config, f.name)):
                missing += undocumented(getattr(config, f.name), f"{prefix}{f.name}.")
        return missing

    assert undocumented(PipelineConfig(Path("IN"), Path("OUT"))) == []
