"""Plain functions and constants that several test files share; fixtures are in conftest.py.

Test files import them with ``from helpers import ...`` (pytest puts tests/ on sys.path).
A test file never imports another test file.
"""

from __future__ import annotations

import json
import shutil
import struct
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
SHARED_DATA = SHARED / "data"
FASTDEPTH_WEIGHTS = SHARED / "weights" / "fastdepth"


# --------------------------------------------------------------------------- analytic scenes (medea_core, mvs_core)


def look_at(eye, target, up=(0.0, -1.0, 0.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at `eye` looking at `target`."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([x, y, z], axis=1)
    pose[:3, 3] = eye
    return pose


def plane_depth(pose: np.ndarray, intrinsics, height: int, width: int, normal, offset) -> np.ndarray:
    """z-depth (H, W) of the world plane normal . X = offset seen from a camera-to-world pose."""
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays_cam = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1)
    rays_world = rays_cam @ pose[:3, :3].T
    normal = np.asarray(normal, dtype=np.float64)
    t = (offset - pose[:3, 3] @ normal) / (rays_world @ normal)
    return t.astype(np.float32)


def wall_texture(seed: int = 0, size: int = 512, extent: float = 6.0):
    """A band-limited random texture of a wall: (image (size, size) float32 in [0, 1], metres
    per texel). The wall spans [-extent / 2, extent / 2]^2 in its own x, y; its finest
    detail (~4 cm) is coarser than a pixel's footprint at a few metres, so views of it do
    not alias."""
    import cv2

    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((size, size)).astype(np.float32)
    image = cv2.GaussianBlur(noise, (0, 0), 3.0) + 0.5 * cv2.GaussianBlur(noise, (0, 0), 8.0)
    image = (image - image.min()) / (image.max() - image.min())
    return image, extent / size


def render_wall(poses, intrinsics, height: int, width: int, distance: float = 3.0, flat_right: bool = False,
                seed: int = 0):
    """Grey images (N, H, W) float32 in [0, 1] and depth (N, H, W) of a textured wall z = distance
    (world frame) seen from camera-to-world poses. flat_right: the wall's half x > 0 is a
    uniform grey (no texture at all), for textureless-surface tests."""
    import cv2

    texture, texel = wall_texture(seed)
    size = texture.shape[0]
    images, depths = [], []
    for pose in poses:
        depth = plane_depth(pose, intrinsics, height, width, normal=[0.0, 0.0, 1.0], offset=distance)
        fx, fy, cx, cy = intrinsics
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        rays = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], -1) * depth[..., None]
        world = rays @ pose[:3, :3].T + pose[:3, 3]
        tx = (world[..., 0] / texel + size / 2).astype(np.float32)
        ty = (world[..., 1] / texel + size / 2).astype(np.float32)
        grey = cv2.remap(texture, tx, ty, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        if flat_right:
            grey = np.where(world[..., 0] > 0, np.float32(0.5), grey)
        images.append(grey)
        depths.append(depth)
    return np.stack(images).astype(np.float32), np.stack(depths).astype(np.float32)


# --------------------------------------------------------------------------- Rerun recordings (viewer, cli)


def read_recording(path) -> tuple[list[str], dict[str, set[str]], dict[str, list[int]], dict[str, dict[str, list]]]:
    """An .rrd read back with rerun's chunk API: entity paths; component columns per entity;
    "frame" values per entity (and "epoch" values under "<entity>#epoch", "time" values in
    seconds under "<entity>#time"); first-row values of every component column per entity.
    Skips the calling test without rerun.chunk. The layout the file opens with:
    :func:`recording_blueprint`."""
    rr_chunk = pytest.importorskip("rerun.chunk", reason="needs rerun-sdk with rerun.chunk (0.41+)")
    reader = rr_chunk.RrdReader(path)
    assert len(reader.recordings()) == 1
    entities = reader.store().schema().entity_paths()
    components: dict[str, set[str]] = defaultdict(set)
    frames: dict[str, list[int]] = defaultdict(list)
    values: dict[str, dict[str, list]] = defaultdict(dict)
    for chunk in reader.stream():
        batch = chunk.to_record_batch()
        names = [n for n in batch.schema.names if ":" in n and not n.startswith("rerun.")]
        components[chunk.entity_path].update(names)
        if "frame" in chunk.timeline_names:
            frames[chunk.entity_path].extend(batch.column("frame").to_pylist())
        for name in names:
            values[chunk.entity_path].setdefault(name, batch.column(name).to_pylist())
        if "epoch" in chunk.timeline_names:
            frames[chunk.entity_path + "#epoch"].extend(batch.column("epoch").to_pylist())
        if "time" in chunk.timeline_names:  # a duration in nanoseconds
            nanoseconds = batch.column("time").cast("int64").to_pylist()
            frames[chunk.entity_path + "#time"].extend(None if t is None else t / 1e9 for t in nanoseconds)
    return entities, components, frames, values


def recording_blueprint(path) -> dict:
    """The layout (Rerun blueprint) an .rrd carries, read with rerun's chunk API; skips the
    calling test without rerun.chunk. Asserts the file holds one blueprint store, of the
    recording's application id.

    Returns {"timeline": the time panel's timeline, "play_state": "Following" | ... | None,
    "root": the root container, "views": every view depth-first, "activation": {"make_active":
    bool, "make_default": bool} from ``rerun rrd print`` of the CLI bundled with rerun-sdk (the
    activation command is no chunk), None without that CLI}. A container is {"type":
    "container", "kind": "Tabs" | "Horizontal" | "Vertical" | "Grid", "name", "contents": [...],
    "active_tab": index or None}; a view {"type": "view", "class": "3D" | "2D" | "TimeSeries" |
    "TextLog" | ..., "name", "origin", "contents": [query lines]}."""
    import uuid

    rr_chunk = pytest.importorskip("rerun.chunk", reason="needs rerun-sdk with rerun.chunk (0.41+)")
    from rerun.blueprint.components import ContainerKind, PlayState

    reader = rr_chunk.RrdReader(path)
    recordings, blueprints = reader.recordings(), reader.blueprints()
    assert len(blueprints) == 1, f"{path}: {len(blueprints)} blueprint stores"
    assert len(recordings) == 1 and blueprints[0].application_id == recordings[0].application_id
    # {blueprint entity: {field: last logged value}}, e.g. {"view/<id>": {"space_origin": ["/world"]}}
    fields: dict[str, dict[str, list]] = defaultdict(dict)
    for chunk in reader.stream(store=blueprints[0]):
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if ":" in name and not name.startswith("rerun."):
                rows = [row for row in batch.column(name).to_pylist() if row is not None]
                if rows:
                    fields[chunk.entity_path.lstrip("/")][name.split(":", 1)[1]] = rows[-1]

    def first(entity: str, field: str):
        value = fields[entity].get(field)
        return value[0] if value else None

    def node(entity: str) -> dict:
        if entity.startswith("view/"):
            return {"type": "view", "class": first(entity, "class_identifier"), "name": first(entity, "display_name"),
                    "origin": first(entity, "space_origin"),
                    "contents": list(fields[f"{entity}/ViewContents"].get("query", []))}
        children = list(fields[entity].get("contents", []))
        active = first(entity, "active_tab")
        return {"type": "container", "kind": ContainerKind(first(entity, "container_kind")).name,
                "name": first(entity, "display_name"), "contents": [node(child) for child in children],
                "active_tab": children.index(active) if active in children else None}

    def walk(item: dict):
        if item["type"] == "view":
            yield item
        else:
            for child in item["contents"]:
                yield from walk(child)

    root_id = first("viewport", "root_container")
    root = node(f"container/{uuid.UUID(bytes=bytes(root_id))}") if root_id else None
    play_state = first("time_panel", "play_state")
    return {
        "timeline": first("time_panel", "timeline"),
        "play_state": PlayState(play_state).name if play_state is not None else None,
        "root": root,
        "views": list(walk(root)) if root else [],
        "activation": _blueprint_activation(path, blueprints[0].recording_id),
    }


def _blueprint_activation(path, blueprint_id: str) -> dict[str, bool] | None:
    """make_active / make_default of the blueprint's activation command, from the bundled CLI."""
    import re
    import subprocess

    try:
        import rerun_cli
    except ImportError:
        return None
    cli = Path(rerun_cli.__file__).parent / "rerun"
    if not cli.is_file():
        return None
    printed = subprocess.run([str(cli), "rrd", "print", str(path)], capture_output=True, text=True, timeout=120,
                             check=True).stdout
    found = re.search(rf'BlueprintActivationCommand\(StoreId\(Blueprint, "[^"]*", "{re.escape(blueprint_id)}"\), '
                      r"make_active: (\w+), make_default: (\w+)\)", printed)
    if found is None:
        return {"make_active": False, "make_default": False}
    return {"make_active": found.group(1) == "true", "make_default": found.group(2) == "true"}


# --------------------------------------------------------------------------- GLB files (export)


def glb_json(data: bytes) -> dict:
    """The JSON chunk of a GLB file's bytes."""
    length = struct.unpack_from("<I", data, 12)[0]
    return json.loads(data[20:20 + length])


def glb_vertex_colors(path) -> np.ndarray:
    """(N, 4) uint8 COLOR_0 of the first primitive, read from the file itself (trimesh drops
    vertex colours when a primitive has a material, which glTF viewers multiply them into)."""
    data = Path(path).read_bytes()
    document = glb_json(data)
    accessor = document["accessors"][document["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"]]
    view = document["bufferViews"][accessor["bufferView"]]
    assert accessor["componentType"] == 5121 and accessor["type"] == "VEC4"  # normalised uint8 RGBA
    binary = 20 + struct.unpack_from("<I", data, 12)[0] + 8
    start = binary + view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    return np.frombuffer(data, np.uint8, accessor["count"] * 4, start).reshape(-1, 4)


# --------------------------------------------------------------------------- frame sources (io video, io frames)

SOURCE_W, SOURCE_H, SOURCE_FPS = 64, 48, 10.0


def source_frame(i: int, w: int = SOURCE_W, h: int = SOURCE_H) -> np.ndarray:
    """RGB frame i: flat grey level 20 + 20 i (survives lossy codecs) and a white square moving right."""
    img = np.full((h, w, 3), 20 + 20 * i, np.uint8)
    x = 4 + 4 * i
    img[8:24, x : x + 16] = 255
    return img


def write_clip(path: Path, n: int, fourcc: str = "mp4v", w: int = SOURCE_W, h: int = SOURCE_H,
               fps: float = SOURCE_FPS) -> Path:
    """A video of source_frame(0 .. n - 1) written with OpenCV."""
    import cv2

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (w, h))
    assert writer.isOpened(), f"cannot write {path} with {fourcc}"
    for i in range(n):
        writer.write(cv2.cvtColor(source_frame(i, w, h), cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def write_images(folder: Path, names, size=(SOURCE_W, SOURCE_H)) -> None:
    """source_frame(i) saved as folder / names[i] (size is W, H)."""
    import cv2

    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        assert cv2.imwrite(str(folder / name), cv2.cvtColor(source_frame(i, *size), cv2.COLOR_RGB2BGR))


def grey_level(rgb: np.ndarray) -> float:
    """Grey level of the frame's bottom rows (away from the moving square)."""
    return float(rgb[-10:].mean())


def one_line(exc: pytest.ExceptionInfo) -> str:
    """The message of a raised error, checked to be one non-empty line."""
    message = str(exc.value)
    assert "\n" not in message and message
    return message


# --------------------------------------------------------------------------- depth priors (priors_*)

PRIOR_H, PRIOR_W = 24, 32


def prior_frames(count: int, height: int = PRIOR_H, width: int = PRIOR_W) -> np.ndarray:
    """Random RGB frames (count, H, W, 3) uint8, the same for the same arguments."""
    return np.random.default_rng(0).integers(0, 255, (count, height, width, 3), dtype=np.uint8)


def prior_depth(count: int, height: int = PRIOR_H, width: int = PRIOR_W) -> np.ndarray:
    """Metric depth (count, H, W) in [0.5, 4.5] m with a hole in each map, millimetre-exact."""
    rng = np.random.default_rng(1)
    depth = np.round(rng.uniform(0.5, 4.5, (count, height, width)), 3).astype(np.float32)
    depth[:, :3, :4] = 0.0
    return depth


def prior_error(prior, frames, *words) -> str:
    """The one-line ReconInputError of prior(frames), checked to name every one of words."""
    from recon.errors import ReconInputError

    with pytest.raises(ReconInputError) as info:
        prior(frames)
    message = str(info.value)
    assert "\n" not in message
    for word in words:
        assert str(word) in message
    return message


def save_tiny_dpt(folder: Path) -> Path:
    """A randomly initialised DPT (affine-invariant disparity, like MiDaS) of a few kB, and its
    image processor, saved as a local Hugging Face model folder. Needs transformers."""
    import transformers as T

    config = T.DPTConfig(hidden_size=16, num_hidden_layers=4, num_attention_heads=2, intermediate_size=32,
                         image_size=32, patch_size=8, backbone_out_indices=[0, 1, 2, 3],
                         neck_hidden_sizes=[8, 8, 8, 8], fusion_hidden_size=8)
    T.DPTForDepthEstimation(config).save_pretrained(folder)
    T.DPTImageProcessor(size={"height": 32, "width": 32}).save_pretrained(folder)
    return folder


def save_tiny_depth_anything(folder: Path) -> Path:
    """A randomly initialised metric Depth Anything (max depth 10 m) of a few kB, and its image
    processor, saved as a local Hugging Face model folder. Needs transformers."""
    import transformers as T

    backbone = T.Dinov2Config(hidden_size=16, num_hidden_layers=4, num_attention_heads=2, mlp_ratio=2,
                              image_size=28, patch_size=14, out_indices=[1, 2, 3, 4], reshape_hidden_states=False)
    config = T.DepthAnythingConfig(backbone_config=backbone, reassemble_hidden_size=16, neck_hidden_sizes=[8, 8, 8, 8],
                                   fusion_hidden_size=8, head_hidden_size=8, depth_estimation_type="metric",
                                   max_depth=10)
    T.DepthAnythingForDepthEstimation(config).save_pretrained(folder)
    T.DPTImageProcessor(size={"height": 28, "width": 28}).save_pretrained(folder)
    return folder


def copy_fastdepth_weights(src: Path, dst: Path) -> Path:
    """A copy of the FastDepth TF.js files of src in the new folder dst; its model.json."""
    dst.mkdir(parents=True)
    for name in ("model.json", "group1-shard1of1.bin"):
        shutil.copy(src / name, dst / name)
    return dst / "model.json"


# --------------------------------------------------------------------------- pose files (io trajectories, io colmap)

POSE_FILE_INTRINSICS = {"fx": 500.0, "fy": 510.0, "cx": 320.5, "cy": 239.5, "width": 640, "height": 480}


def random_poses(n=6, seed=0):
    """n random camera-to-world poses (random rotations, unit-normal positions)."""
    from scipy.spatial.transform import Rotation

    from recon.geometry.rigid import make_poses

    rng = np.random.default_rng(seed)
    return make_poses(Rotation.random(n, random_state=seed).as_matrix(), rng.normal(size=(n, 3)))


# --------------------------------------------------------------------------- output folders (export, io output_folder)


def no_temp_files(folder: Path) -> bool:
    """Whether nothing under folder is a hidden (temporary) file, as atomic writes leave none."""
    return not any(p.name.startswith(".") for p in folder.rglob("*"))
