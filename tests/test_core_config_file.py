"""`recon run --config FILE` (recon.core.config_file): report.json's options reproduce a run's
config exactly, YAML sections per stage, flags over the file, bad files in one line; and the
command line's defaults are the config's."""

import json
from pathlib import Path

import pytest

from recon.commands.cli import main
from recon.commands.cli_args import build_parser, pipeline_config_from_args
from recon.core.config import PipelineConfig

RICH = ["--stride", "2", "--max-frames", "40", "--stream", "off", "--fov", "62.5", "--distortion", "0.1,-0.02,0,0",
        "--poses", "given.txt", "--pose-option", "window=6", "--prior", "sensor", "--preset", "paper",
        "--stage1-epochs", "30", "--refine-option", "num_sources=3", "--voxel-size", "0.01", "--max-triangles", "5000",
        "--no-npy", "--on-break", "stop", "--quiet"]


def _config(*argv: str) -> PipelineConfig:
    return pipeline_config_from_args(build_parser().parse_args(["run", *argv]))


@pytest.fixture(autouse=True)
def _plain_machine(monkeypatch):
    """--device auto and the Rerun default depend on the machine: pin them to a CPU box
    without a display, so that the comparisons mean the same everywhere."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    monkeypatch.setattr("recon.commands.cli_args.default_rerun_mode", lambda: "off")


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
    code = main(["run", str(tmp_path / "missing.mp4"), "-o", str(tmp_path / "out"), "--config", str(path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("recon: error:") and expected in err[0], err
    assert not (tmp_path / "out").exists()
