"""The output folder (recon.io.output_folder): depth PNGs in millimetres, refusing to write
into a folder that holds other files, and atomic writes that never leave half a file."""

from __future__ import annotations

import json

import numpy as np
import open3d as o3d
import pytest

from recon.errors import ReconInputError
from recon.export import glb_bytes, write_mesh_ply
from recon.io.depth_maps import depth_to_mm, read_depth_file, read_depth_png_mm
from recon.io.output_folder import OutputFolder, atomic_write_bytes

from helpers import no_temp_files


def test_depth_png_round_trip(tmp_path):
    depth = np.array([[0.0, 1.2344, 0.0004], [np.nan, 70.0, -1.0], [np.inf, 65.535, 2.5]], np.float32)
    mm = depth_to_mm(depth)
    # Beyond 65.534 m clipped there: 65535 means "no measurement" to depth readers (ours too).
    assert mm.tolist() == [[0, 1234, 1], [0, 65534, 0], [0, 65534, 2500]]
    out = OutputFolder(tmp_path / "o")
    from recon.export import write_depth_frame

    png, npy = write_depth_frame(out, "f", depth)
    back = read_depth_png_mm(png)
    assert back.dtype == np.float32 and back[0, 1] == pytest.approx(1.234) and back[1, 1] == pytest.approx(65.534)
    assert np.array_equal(back > 0, np.isfinite(depth) & (depth > 0))
    np.testing.assert_allclose(read_depth_file(png), back, rtol=1e-6)  # what --prior folder reads of it
    stored = np.load(npy)
    assert stored.dtype == np.float32 and stored[1, 0] == 0 and stored[1, 1] == 70.0 and stored[2, 0] == 0


def test_output_folder_refuses_non_empty(tmp_path):
    target = tmp_path / "busy"
    target.mkdir()
    (target / "keep.txt").write_text("precious")
    with pytest.raises(ReconInputError) as exc:
        OutputFolder(target)
    assert str(target) in str(exc.value) and "\n" not in str(exc.value)
    assert (target / "keep.txt").read_text() == "precious"
    # With overwrite: same names replaced, other files left alone.
    out = OutputFolder(target, overwrite=True)
    out.write_text("keep2.txt", "new")
    assert (target / "keep.txt").read_text() == "precious"
    # An empty existing folder and a new nested one are fine; a file is not.
    (tmp_path / "empty").mkdir()
    OutputFolder(tmp_path / "empty")
    assert OutputFolder(tmp_path / "a" / "b").path.is_dir()
    (tmp_path / "file").write_text("x")
    with pytest.raises(ReconInputError):
        OutputFolder(tmp_path / "file")


def test_atomic_writes(tmp_path):
    out = OutputFolder(tmp_path / "o")
    out.write_json("r.json", {"a": 1})
    out.write_json("r.json", {"a": 2})  # this run's own file may be rewritten
    assert json.loads((out.path / "r.json").read_text()) == {"a": 2}
    # A writer that fails leaves neither a temp file nor a partial result.
    with pytest.raises(RuntimeError):
        with out.atomic("broken.bin") as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("writer crashed")
    assert not (out.path / "broken.bin").exists()
    # Standalone writers never replace an existing file without overwrite.
    target = tmp_path / "o" / "existing.ply"
    target.write_text("old")
    mesh = o3d.geometry.TriangleMesh.create_tetrahedron()
    with pytest.raises(ReconInputError):
        write_mesh_ply(target, mesh)
    assert target.read_text() == "old"
    with pytest.raises(ReconInputError):
        atomic_write_bytes(target, b"new")
    assert target.read_text() == "old"
    write_mesh_ply(target, mesh, overwrite=True)
    assert len(o3d.io.read_triangle_mesh(str(target)).triangles) == 4
    assert glb_bytes(mesh)[:4] == b"glTF"
    assert no_temp_files(out.path)
    with pytest.raises(ValueError):
        out.path_for("../escape.txt")


def test_stale_results_name_what_this_run_did_not_write(tmp_path):
    from recon.io.output_folder import stale_results

    for name in ("segment_00", "segment_01", "segment_02", "segment_notes"):
        (tmp_path / name).mkdir()
    (tmp_path / "mesh.ply").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("the user's")
    # A single reconstruction: every segment folder is an earlier run's, its own mesh is not.
    assert stale_results(tmp_path, []) == ["segment_00", "segment_01", "segment_02"]
    # Two segments: the third, and the top-level mesh of an earlier single run.
    assert stale_results(tmp_path, ["segment_00", "segment_01"]) == ["mesh.ply", "segment_02"]


def test_an_earlier_run_is_known_by_its_report(tmp_path):
    """earlier_run_files: the report, what it lists, the depth maps of the frames it names,
    a listed segment folder's own list; nothing without a readable report, nothing outside
    the folder. remove_earlier_run leaves a file written again since the new run began."""
    import os
    import time

    from recon.io.earlier_run import earlier_run_files, remove_earlier_run

    assert earlier_run_files(tmp_path) == []
    (tmp_path / "report.json").write_text("not json")
    assert earlier_run_files(tmp_path) == []
    (tmp_path / "depth").mkdir()
    for name in ("mesh.ply", "depth/a.png", "depth/a.npy", "depth/b.png", "depth/user.png", "other.txt"):
        (tmp_path / name).write_text("x")
    (tmp_path / "report.json").write_text(json.dumps({
        "files": {"mesh_ply": "mesh.ply", "depth": "depth", "recording": "/elsewhere/run.rrd"},
        "frames": {"names": ["a", "b"]}}))
    found = sorted(str(p.relative_to(tmp_path)) for p in earlier_run_files(tmp_path))
    assert found == ["depth/a.npy", "depth/a.png", "depth/b.png", "mesh.ply", "report.json"]
    files = earlier_run_files(tmp_path)
    started = time.time()
    os.utime(tmp_path / "mesh.ply", (started + 5, started + 5))  # written again by the new run
    removed = remove_earlier_run(tmp_path, files, started)
    assert sorted(p.name for p in removed) == ["a.npy", "a.png", "b.png", "report.json"]
    assert sorted(p.name for p in tmp_path.rglob("*") if p.is_file()) == ["mesh.ply", "other.txt", "user.png"]
