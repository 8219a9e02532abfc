"""The synthetic renderer: ray casting the room (Open3D ``RaycastingScene``) into colour and
exact z-depth, and :func:`render_sequence`, which renders the hand-held camera path, with
optional motion blur, into the :class:`SyntheticSequence` it returns with its ground truth.
Writing its frames as a video is :func:`recon.io.video.write_video`.

Everything follows the package conventions (camera-to-world poses, z-depth, intrinsics
fx, fy, cx, cy with pixel centres at integer coordinates, so the principal point of a
centred camera is ((W-1)/2, (H-1)/2)). Shading is Lambertian with fixed point lights, and
textures depend only on the surface point, so a surface point has the same colour in
every view.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from ..errors import ReconInputError
from .camera import camera_path, intrinsics_for
from .room import ROOM_HALF_X, ROOM_HALF_Z, ROOM_HEIGHT, Materials, raycasting_scene, scene_layout, scene_mesh
from .textures import TEXEL, MipAtlas, texture_pyramid

_LIGHTS = np.array([[-1.6, -2.55, -1.1], [1.7, -2.55, 1.2], [0.3, -2.55, -1.9]], dtype=np.float32)
_LIGHT_POWER = np.array([0.75, 0.75, 0.5], dtype=np.float32)
_LIGHT_FALLOFF = 2.5  # metres at which a light's irradiance halves
_AMBIENT = 0.35
_CHUNK_PIXELS = 1_250_000  # pixels ray-cast and shaded per batch: ~150 MB of temporaries


def room_lights(centre=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """The room's ceiling lights for a room whose floor centre is `centre` (3,): positions
    (3, 3) float32 and powers (3,) float32."""
    return _LIGHTS + np.asarray(centre, dtype=np.float32), _LIGHT_POWER.copy()


@dataclass
class SyntheticSequence:
    """A rendered sequence with its ground truth.

    Attributes:
        rgb: (N, H, W, 3) uint8 frames.
        depth: (N, H, W) float32 z-depth in metres, > 0 everywhere (the room is closed).
        poses: (N, 4, 4) float64 camera-to-world poses (OpenCV camera axes).
        intrinsics: (fx, fy, cx, cy) in pixels; cx = (W-1)/2, cy = (H-1)/2.
        mesh_vertices: (V, 3) float64 ground-truth mesh vertices, world coordinates
            (y down, floor at y = 0; see recon.synthetic.room). Exactly the rendered
            geometry: the room's faces reach 5 cm past its edges (outside, never seen);
            box faces flush with the floor, a wall or a supporting box are left out.
        mesh_triangles: (F, 3) int64 vertex indices, counter-clockwise seen from the
            visible side (normals point into free space).
        mesh_colors: (V, 3) float64 in [0, 1], each object's base colour.
        triangle_materials: (F,) int64 material id of each triangle.
        boxes: (B, 2, 3) float64 min and max corners of the furniture boxes.
        seed: the scene seed.
        room_bounds: (2, 3) float64 min and max corners of the room.
    """

    rgb: np.ndarray
    depth: np.ndarray
    poses: np.ndarray
    intrinsics: tuple[float, float, float, float]
    mesh_vertices: np.ndarray
    mesh_triangles: np.ndarray
    mesh_colors: np.ndarray
    triangle_materials: np.ndarray
    boxes: np.ndarray
    seed: int = 0
    room_bounds: np.ndarray = field(
        default_factory=lambda: np.array([[-ROOM_HALF_X, -ROOM_HEIGHT, -ROOM_HALF_Z], [ROOM_HALF_X, 0.0, ROOM_HALF_Z]])
    )

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 pinhole matrix."""
        fx, fy, cx, cy = self.intrinsics
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def num_frames(self) -> int:
        return self.rgb.shape[0]

    @property
    def height(self) -> int:
        return self.rgb.shape[1]

    @property
    def width(self) -> int:
        return self.rgb.shape[2]

    def o3d_mesh(self) -> o3d.geometry.TriangleMesh:
        """The ground-truth mesh as a legacy Open3D TriangleMesh with vertex colours and normals."""
        mesh = o3d.geometry.TriangleMesh(
            o3d.utility.Vector3dVector(self.mesh_vertices),
            o3d.utility.Vector3iVector(self.mesh_triangles.astype(np.int32)),
        )
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.mesh_colors)
        mesh.compute_triangle_normals()
        mesh.compute_vertex_normals()
        return mesh

    def raycasting_scene(self) -> o3d.t.geometry.RaycastingScene:
        """A RaycastingScene of the ground-truth mesh (for distances, extra rays)."""
        return raycasting_scene(self.mesh_vertices, self.mesh_triangles)


def _camera_rays(intrinsics, width: int, height: int) -> np.ndarray:
    """(H*W, 3) float64 camera-frame ray directions with unit z through the pixel centres."""
    fx, fy, cx, cy = intrinsics
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1).reshape(-1, 3)


def _pick(axis: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Per point, the component (x, y or z) along its face axis (P,)."""
    return np.where(axis == 0, x, np.where(axis == 1, y, z))


def _irradiance(px, py, pz, axis, facing, p_axis, lights=_LIGHTS, powers=_LIGHT_POWER) -> np.ndarray:
    """Lambertian irradiance (P,) from ambient light and point lights at points (px, py, pz)
    on axis-aligned faces whose visible normal is `facing` (+1/-1) along `axis`; p_axis is
    the points' coordinate along that axis. lights: (L, 3) float32 positions, powers (L,)."""
    irradiance = np.full(len(px), _AMBIENT, dtype=np.float32)
    for light, power in zip(lights, powers):
        dist2 = np.square(light[0] - px)
        dist2 += np.square(light[1] - py)
        dist2 += np.square(light[2] - pz)
        # n . (light - p) for an axis-aligned normal is one signed component.
        along = light[axis] - p_axis
        along *= facing
        np.maximum(along, 0.0, out=along)
        falloff = dist2 * np.float32(1.0 / _LIGHT_FALLOFF**2) + 1.0
        falloff *= np.sqrt(dist2)
        along *= np.float32(power)
        along /= falloff
        irradiance += along
    return irradiance


def _albedo(params: np.ndarray, tex: np.ndarray) -> list[np.ndarray]:
    """Albedo channels [r, g, b], each (P,), from per-point material parameters (12, P)
    (rows as in Materials.table) and texture samples (P, 4)."""
    mix = np.clip(0.5 + 0.4 * tex[:, 1], 0.0, 1.0)
    pattern = 1.0 + params[7] * (tex[:, 2] - 0.5)
    pattern += params[8] * (tex[:, 3] - 0.5)
    lum = np.exp(params[6] * tex[:, 0])
    lum *= pattern
    return [(params[c] + (params[3 + c] - params[c]) * mix) * lum for c in range(3)]


# Linear intensity -> 8-bit with a display gamma (dark regions keep visible texture).
_GAMMA_STEPS = 4096
_GAMMA_LUT = np.round(255.0 * (np.arange(_GAMMA_STEPS) / (_GAMMA_STEPS - 1)) ** (1 / 2.2)).astype(np.uint8)


def _encode(linear: np.ndarray) -> np.ndarray:
    index = np.clip(linear, 0.0, 1.0)
    index *= _GAMMA_STEPS - 1
    index += 0.5
    return _GAMMA_LUT[index.astype(np.int32)]


# Shading runs over blocks of this many pixels: their temporaries stay in the CPU cache,
# which makes the long chain of elementwise numpy operations several times faster.
_SHADE_BLOCK = 16384


class Renderer:
    """Renders frames of one scene; holds the ray-casting scene, per-triangle data and textures.

    lights: point lights as positions (L, 3) and powers (L,), default the room's three
    ceiling lights (recon.synthetic.walkthrough lights several rooms).
    """

    def __init__(
        self, vertices, triangles, triangle_materials, materials: Materials, pyramid, intrinsics, width, height,
        lights: tuple[np.ndarray, np.ndarray] | None = None,
    ):
        self.scene = raycasting_scene(vertices, triangles)
        positions, powers = (_LIGHTS, _LIGHT_POWER) if lights is None else lights
        self.lights = np.asarray(positions, dtype=np.float32).reshape(-1, 3)
        self.light_powers = np.asarray(powers, dtype=np.float32).reshape(-1)
        corners = vertices[triangles]
        normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        self.triangle_axis = np.abs(normals).argmax(axis=1).astype(np.int64)
        self.triangle_params_t = np.ascontiguousarray(materials.table()[triangle_materials].T)  # (12, F)
        self.atlas = MipAtlas(pyramid)
        rays = _camera_rays(intrinsics, width, height)
        self.ray_x, self.ray_y = rays[:, 0].astype(np.float32), rays[:, 1].astype(np.float32)
        self.ray_norm = np.linalg.norm(rays, axis=1).astype(np.float32)
        # A fronto-parallel surface at depth d covers d / (|ray| * f) metres per pixel.
        self.footprint = 1.0 / (self.ray_norm * np.float32(intrinsics[0]))
        self.shape = (height, width)

    def render(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """rgb (n, H, W, 3) uint8 and z-depth (n, H, W) float32 for poses (n, 4, 4)."""
        n, pixels = len(poses), len(self.ray_x)
        origin = poses[:, :3, 3].astype(np.float32)[:, :, None]  # (n, 3, 1)
        rot = poses[:, :3, :3].astype(np.float32)[:, :, :, None]  # (n, 3, 3, 1)
        # Components are kept as separate contiguous arrays: much faster than (P, 3) columns.
        d = [rot[:, k, 0] * self.ray_x + rot[:, k, 1] * self.ray_y + rot[:, k, 2] for k in range(3)]  # 3 x (n, P)
        rays = np.empty((n, pixels, 6), dtype=np.float32)
        for k in range(3):
            rays[:, :, k] = origin[:, k]
            rays[:, :, 3 + k] = d[k]
        hit = self.scene.cast_rays(o3d.core.Tensor(rays.reshape(-1, 6)))
        del rays
        # Ray directions have unit z in the camera frame, so the ray parameter is the z-depth.
        depth = hit["t_hit"].numpy().reshape(n, pixels)
        if not np.isfinite(depth).all():
            raise RuntimeError("synthetic renderer: a ray left the room (camera outside?)")
        prim = hit["primitive_ids"].numpy().reshape(-1)
        points = [(origin[:, k] + d[k] * depth).reshape(-1) for k in range(3)]
        dirs = [c.reshape(-1) for c in d]
        flat_depth = depth.reshape(-1)
        rgb = np.empty((n * pixels, 3), dtype=np.uint8)
        for start in range(0, n * pixels, _SHADE_BLOCK):
            block = slice(start, start + _SHADE_BLOCK)
            pix = np.arange(start, min(start + _SHADE_BLOCK, n * pixels)) % pixels
            rgb[block] = self._shade(
                [c[block] for c in points], [c[block] for c in dirs], prim[block].astype(np.int64), flat_depth[block],
                pix,
            )
        return rgb.reshape(n, *self.shape, 3), depth.reshape(n, *self.shape)

    def _shade(self, points, dirs, prim, depth, pix) -> np.ndarray:
        """Colours (P, 3) uint8 of ray hits: points and ray directions as 3 x (P,), triangle
        ids, depths and pixel indices (P,)."""
        px, py, pz = points
        axis = self.triangle_axis[prim]
        d_axis = _pick(axis, *dirs)
        # The visible side of a face is the one facing the camera; closed solids are only
        # seen from outside, so this is view-independent.
        facing = np.where(d_axis > 0, np.float32(-1.0), np.float32(1.0))
        cos = np.abs(d_axis) / self.ray_norm[pix]
        params = np.take(self.triangle_params_t, prim, axis=1)  # (12, P)
        tex = self._texture(px, py, pz, axis, params, depth * self.footprint[pix], cos)
        irradiance = _irradiance(px, py, pz, axis, facing, _pick(axis, px, py, pz), self.lights, self.light_powers)
        rgb = np.empty((len(px), 3), dtype=np.uint8)
        for c, albedo in enumerate(_albedo(params, tex)):
            np.clip(albedo, 0.02, 1.0, out=albedo)
            albedo *= irradiance
            rgb[:, c] = _encode(albedo)
        return rgb

    def _texture(self, px, py, pz, axis, params, footprint, cos) -> np.ndarray:
        """Texture samples (P, 4) at hit points on faces normal to axis (P,) with material
        parameters (12, P)."""
        # In-plane coordinates: horizontal first, so stripes along u are vertical on walls.
        u = np.where(axis == 0, pz, px)
        v = np.where(axis == 1, pz, py)
        scale = params[9]
        u = u * scale + params[10]
        v = v * scale + params[11]
        # Mip level from the pixel footprint; the square root splits a grazing view's
        # stretch between blur and aliasing.
        footprint *= scale
        footprint /= np.sqrt(np.maximum(cos, 0.05))
        level = np.log2(np.maximum(footprint, 1e-6) * np.float32(1.0 / TEXEL))
        return self.atlas.sample(u, v, level)


def render_sequence(
    num_frames: int = 120,
    width: int = 640,
    height: int = 480,
    seed: int = 0,
    chunk: int | None = None,
    threads: int = 2,
    speed: float = 1.0,
    blur: int = 1,
    exposure: float = 0.5,
) -> SyntheticSequence:
    """Render the synthetic room along the hand-held camera path.

    Args:
        num_frames: N >= 1; the path advances ~2 cm and ~0.4 degrees of yaw per frame
            (times `speed`).
        speed: motion per frame relative to the default path (a fast hand-held walk: 4-8).
        blur: sub-frames rendered and averaged per frame, spread over `exposure` (a
            fraction of the frame interval) centred on the frame's time: motion blur.
            The pose, depth and mesh are those of the frame's time (the middle of the
            exposure); 1 renders sharp frames.
        width, height: image size in pixels (>= 8); fx = fy = 525 * width / 640,
            cx = (width - 1) / 2, cy = (height - 1) / 2.
        seed: scene layout, colours, textures and path phases; the same seed gives
            bit-identical output.
        chunk: frames ray-cast per batch (memory vs. overhead); default: about 1.2
            million pixels, fewer if that leaves a thread idle.
        threads: batches rendered concurrently.

    Returns:
        a SyntheticSequence with rgb (N, H, W, 3) uint8, depth (N, H, W) float32, poses
        (N, 4, 4) camera-to-world in a y-down world frame, intrinsics and the ground-truth
        mesh.
    """
    if int(num_frames) < 1:
        raise ReconInputError(f"synthetic sequence: num_frames must be >= 1, got {num_frames}")
    if int(width) < 8 or int(height) < 8:
        raise ReconInputError(f"synthetic sequence: image size must be at least 8x8, got {width}x{height}")
    num_frames, width, height, seed = int(num_frames), int(width), int(height), int(seed)
    boxes, materials, room = scene_layout(seed)
    vertices, triangles, triangle_materials = scene_mesh(boxes, room)
    intrinsics = intrinsics_for(width, height)
    blur = int(blur)
    if blur < 1 or not (0.0 <= exposure <= 1.0) or not speed > 0:
        raise ReconInputError(f"synthetic sequence: need blur >= 1, 0 <= exposure <= 1 and speed > 0, got "
                              f"blur={blur}, exposure={exposure}, speed={speed}")
    times = np.arange(num_frames, dtype=np.float64) * float(speed)
    poses = camera_path(num_frames, seed, times=times)
    # Sub-frame times, frame-major: blur steps evenly over the exposure around each frame.
    offsets = (np.arange(blur) + 0.5) / blur - 0.5 if blur > 1 else np.zeros(1)
    sub_poses = camera_path(0, seed, times=(times[:, None] + offsets * exposure * float(speed)).reshape(-1))
    renderer = Renderer(vertices, triangles, triangle_materials, materials, texture_pyramid(seed), intrinsics, width,
                        height)
    rgb = np.empty((num_frames, height, width, 3), dtype=np.uint8)
    depth = np.empty((num_frames, height, width), dtype=np.float32)
    threads = max(1, int(threads))
    if chunk is None:
        chunk = min(max(_CHUNK_PIXELS // (width * height * blur), 1), -(-num_frames // threads))
    chunk = max(1, int(chunk))
    starts = range(0, num_frames, chunk)

    def work(start: int) -> None:
        stop = min(start + chunk, num_frames)
        if blur == 1:
            rgb[start:stop], depth[start:stop] = renderer.render(poses[start:stop])
            return
        colour, _ = renderer.render(sub_poses[start * blur : stop * blur])
        # Averaged in linear light would be more exact; the renderer's output is what a
        # camera integrates well enough for a tracking test.
        rgb[start:stop] = colour.reshape(stop - start, blur, height, width, 3).mean(1).round().astype(np.uint8)
        depth[start:stop] = renderer.render(poses[start:stop])[1]

    # numpy, OpenCV and Open3D release the GIL in their kernels, so two chunks in flight
    # keep both cores of a small machine busy; chunks are independent, so output is identical.
    with ThreadPoolExecutor(max_workers=min(threads, len(starts))) as pool:
        list(pool.map(work, starts))
    colors = np.zeros_like(vertices)
    colors[triangles.reshape(-1)] = np.repeat(materials.color_a[triangle_materials], 3, axis=0)
    return SyntheticSequence(
        rgb=rgb,
        depth=depth,
        poses=poses,
        intrinsics=intrinsics,
        mesh_vertices=vertices,
        mesh_triangles=triangles,
        mesh_colors=colors,
        triangle_materials=triangle_materials,
        boxes=np.array([[b.lo, b.hi] for b in boxes], dtype=np.float64).reshape(-1, 2, 3),
        seed=seed,
    )
