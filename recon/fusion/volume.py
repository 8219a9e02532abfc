"""One TSDF volume that grows frame by frame: integration of a depth map (and colour) at a
time, marching-cubes extraction at any moment, and the removal of small disconnected
fragments from what is extracted.

:func:`recon.fusion.tsdf.fuse` fills one volume from a whole sequence; the streamed pipeline
(:mod:`recon.drivers.streamed`) keeps one open for the whole video, integrates each frame as its depth
is finalised and extracts the mesh every so often for the live viewer. The choice of voxel
size, truncation and depth range is :mod:`recon.fusion.tsdf`'s.
"""

from __future__ import annotations

import math

import numpy as np
import open3d as o3d
import open3d.core as o3c

# Ray casting's range map resolution (render_depth): full resolution. With Open3D's default
# of 8 a different 2-10 % of the rays came back empty or on another surface from one call to
# the next (0 % at factors 1 and 2 over repeated calls); 1 costs ~30 % more on a call that
# takes ~20 ms at 256x192.
RANGE_MAP_DOWN_FACTOR = 1
# Open3D's ray casting splits the blocks' screen footprints into tiles of 16 x 16 range-map
# pixels (RANGE_TILE) held in a fixed buffer (65535); with many blocks in view at once it
# crashed the process. render_depth casts the blocks in front of the camera and in view in
# passes of at most RANGE_TILE_BUDGET tiles (measured: docs/history/validation.md).
RANGE_TILE = 16
RANGE_TILE_BUDGET = 32_768
# Marching cubes and the cleanup after it hold about 0.25 GB per million triangles extracted:
# by default a surface estimated above this many times the triangle budget is meshed at a
# higher weight threshold (FusionOptions.max_extracted, bounded_weight).
# why: docs/decisions.md#the-frames-a-meshed-voxel-needs
EXTRACTION_BUDGET_FACTOR = 4
# Voxel blocks read per pass when counting the surface (bounds the copy: 4 MB of tsdf).
_COUNT_CHUNK = 2048


def clean_depth(d) -> np.ndarray:
    """Depth with NaN, inf and negative values set to 0 (invalid).

    Args:
        d: (H, W) depth in metres.

    Returns:
        (H, W) float32 C-contiguous depth in metres, 0 = invalid.
    """
    d = np.ascontiguousarray(d, dtype=np.float32)
    bad = ~np.isfinite(d) | (d < 0)
    if bad.any():
        d = d.copy()
        d[bad] = 0.0
    return d


def _color_image(rgb_frame, h: int, w: int, device: o3c.Device) -> o3d.t.geometry.Image:
    """(H, W, 3) uint8 -> float32 [0, 1] Open3D image (float depth needs float colour)."""
    import cv2

    c = np.asarray(rgb_frame)
    scale = 1.0 / 255.0 if c.dtype == np.uint8 else 1.0
    if c.shape[:2] != (h, w):
        # Colour at another resolution than depth covers the same field of view: resample it.
        c = cv2.resize(c, (w, h), interpolation=cv2.INTER_AREA)
    c = np.ascontiguousarray(c, dtype=np.float32) * np.float32(scale)
    return o3d.t.geometry.Image(o3c.Tensor(c).to(device))


def _extract(extract, empty_type):
    """Legacy geometry from an Open3D extraction; an empty one when nothing passes the weight test.

    Open3D raises instead of returning an empty result when no voxel qualifies (it cannot
    set a (0,) attribute), so that one error is turned into an empty geometry.
    """
    try:
        return extract().cpu().to_legacy()
    except RuntimeError as exc:
        if "shape {0}" in str(exc):
            return empty_type()
        raise


# --------------------------------------------------------------------------- mesh cleanup


def triangle_components(triangles: np.ndarray, num_vertices: int) -> np.ndarray:
    """Connected-component label of each triangle, triangles sharing a vertex being connected.

    Args:
        triangles: (F, 3) vertex indices.
        num_vertices: number of vertices of the mesh.

    Returns:
        (F,) int component labels.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    # 32-bit indices where they fit: the graph's arrays are the labelling's memory.
    t = np.asarray(triangles, dtype=np.int32 if num_vertices < 2**31 else np.int64)
    rows = np.concatenate([t[:, 0], t[:, 1]])
    cols = np.concatenate([t[:, 1], t[:, 2]])
    graph = coo_matrix((np.ones(len(rows), np.int8), (rows, cols)), shape=(num_vertices, num_vertices))
    _, vertex_label = connected_components(graph, directed=False)
    return vertex_label[t[:, 0]]


def remove_fragments(
    mesh: o3d.geometry.TriangleMesh, min_triangles: int = 100, min_fraction: float = 0.005
) -> tuple[o3d.geometry.TriangleMesh, int]:
    """Drop connected components smaller than `min_triangles` or `min_fraction` of the largest.

    Components are triangles linked through shared vertices (marching cubes shares vertices
    between neighbours), found with scipy's sparse connected components: ~20x faster than
    TriangleMesh.cluster_connected_triangles on big meshes.

    Args:
        mesh: legacy TriangleMesh, changed in place.
        min_triangles: smallest component kept, in triangles.
        min_fraction: smallest component kept, as a share of the largest one's triangles.

    Returns:
        (mesh, number of triangles removed); 0 and 0 keep everything.
    """
    if len(mesh.triangles) == 0 or (min_triangles <= 0 and min_fraction <= 0):
        return mesh, 0
    tri = np.asarray(mesh.triangles)
    cluster_of = triangle_components(tri, len(mesh.vertices))
    sizes = np.bincount(cluster_of)
    keep_cluster = sizes >= max(min_triangles, min_fraction * sizes.max())
    drop = ~keep_cluster[cluster_of]
    removed = int(drop.sum())
    if removed:
        mesh.remove_triangles_by_mask(drop)
        mesh.remove_unreferenced_vertices()
    return mesh, removed


# --------------------------------------------------------------------------- the volume


def blocks_in_view(keys: np.ndarray, side: float, pose, intrinsics, size: tuple[int, int],
                   max_depth: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Voxel blocks wholly in front of a camera, within max_depth and overlapping its image.

    Args:
        keys: (B, 3) integer block coordinates (a block spans keys * side to (keys + 1) * side).
        side: a block's edge in metres.
        pose: (4, 4) camera-to-world.
        intrinsics: (fx, fy, cx, cy) in pixels of an image of `size`.
        size: (H, W) of the image.
        max_depth: metres.

    Returns:
        ((B,) bool: the blocks kept; (K,) float: the range-map tiles each kept block's bounding
        sphere covers at full resolution; (K,) float: each kept block's centre depth).
    """
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    world_to_camera = np.linalg.inv(np.asarray(pose, np.float64))
    centres = (np.asarray(keys, np.float64) + 0.5) * side @ world_to_camera[:3, :3].T + world_to_camera[:3, 3]
    radius = 0.5 * np.sqrt(3.0) * side
    z = centres[:, 2]
    ahead = (z > radius) & (z - radius < max_depth)
    z_safe = np.where(ahead, z, 1.0)
    reach = max(fx, fy) * radius / z_safe
    u, v = fx * centres[:, 0] / z_safe + cx, fy * centres[:, 1] / z_safe + cy
    h, w = size
    seen = ahead & (u + reach >= 0) & (u - reach <= w) & (v + reach >= 0) & (v - reach <= h)
    per_side = np.ceil(2.0 * reach[seen] / RANGE_TILE) + 1  # one more for where it falls on the tile grid
    return seen, per_side * per_side, z[seen]


def tile_batches(tiles: np.ndarray, budget: int) -> list[np.ndarray]:
    """Consecutive runs of blocks whose range-map tiles each sum to at most ``budget``.

    Args:
        tiles: (K,) tiles of each block, in the order the runs take them.
        budget: the tiles a run may start in (it ends with the block that crosses it).

    Returns:
        Index arrays into ``tiles``, one per run, covering every block once.
    """
    # A block joins the run in which its first tile falls: each run stays within the budget
    # plus one block's tiles.
    first = np.cumsum(tiles) - tiles
    run = np.floor(first / budget).astype(np.int64)
    return [np.flatnonzero(run == r) for r in np.unique(run)]


class TsdfVolume:
    """An Open3D VoxelBlockGrid of tsdf, weight (and colour) that frames are integrated into.

    voxel, trunc, max_depth: metres; capacity: voxel blocks allocated up front (the hash map
    grows past it when needed); colored: keep a colour per voxel; device: an Open3D device.
    """

    def __init__(self, voxel: float, trunc: float, max_depth: float, capacity: int, *, colored: bool = True,
                 block_resolution: int = 8, device: o3c.Device | None = None):
        self.voxel, self.trunc, self.max_depth = float(voxel), float(trunc), float(max_depth)
        self.colored = colored
        self.device = device or o3c.Device("CPU:0")
        names = ("tsdf", "weight", "color") if colored else ("tsdf", "weight")
        channels = ((1,), (1,), (3,)) if colored else ((1,), (1,))
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            names, (o3c.float32,) * len(names), channels, voxel_size=self.voxel, block_resolution=block_resolution,
            block_count=int(capacity), device=self.device,
        )
        self.frames_fused = 0
        self.block_resolution = int(block_resolution)

    def integrate(self, depth, pose, intrinsics, rgb=None, weight=None) -> bool:
        """Fuse one frame into the volume.

        Open3D adds one observation per integration, so a pixel of weight w is integrated w
        times, each time with the pixels of weight below that count left out.

        Args:
            depth: (H, W) depth in metres, 0 = invalid.
            pose: (4, 4) camera-to-world.
            intrinsics: (fx, fy, cx, cy) in pixels of the depth.
            rgb: (H', W', 3) uint8 colour (resampled to (H, W)), or None.
            weight: (H, W) integer observations each pixel counts for (None: 1 each; 0 leaves a
                pixel out).

        Returns:
            False when the frame has no valid depth within max_depth (nothing fused; Open3D
            raises on it), else True.
        """
        d = clean_depth(depth)
        if weight is not None:
            weight = np.asarray(weight)
            d = np.where(weight > 0, d, np.float32(0.0))
        if not ((d > 0) & (d <= self.max_depth)).any():
            return False
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        K = o3c.Tensor(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), o3c.float64)
        # Open3D wants the extrinsic world-to-camera matrix.
        E = o3c.Tensor(np.linalg.inv(np.asarray(pose, np.float64)), o3c.float64)
        trunc_mult = self.trunc / self.voxel
        d_img = o3d.t.geometry.Image(o3c.Tensor(d).to(self.device))
        blocks = self.grid.compute_unique_block_coordinates(d_img, K, E, 1.0, self.max_depth, trunc_mult)
        color = _color_image(rgb, *d.shape, self.device) if self.colored and rgb is not None else None
        for count in range(1, 2 if weight is None else int(weight.max()) + 1):
            if count > 1:
                d_count = np.where(weight >= count, d, np.float32(0.0))
                if not ((d_count > 0) & (d_count <= self.max_depth)).any():
                    break
                d_img = o3d.t.geometry.Image(o3c.Tensor(d_count).to(self.device))
            if color is not None:
                self.grid.integrate(blocks, d_img, color, K, K, E, 1.0, self.max_depth, trunc_mult)
            else:
                self.grid.integrate(blocks, d_img, K, E, 1.0, self.max_depth, trunc_mult)
        self.frames_fused += 1
        return True

    def render_depth(self, pose, intrinsics, size: tuple[int, int], min_weight: float = 2.0) -> np.ndarray:
        """Depth of the fused surface seen from a camera, by ray casting.

        Ray casting through the volume's active blocks (Open3D's VoxelBlockGrid.ray_cast).

        Args:
            pose: (4, 4) camera-to-world.
            intrinsics: (fx, fy, cx, cy) in pixels of an image of `size`.
            size: (H, W) of the rendered image.
            min_weight: the fewest observations of a surface a ray may stop on.

        Returns:
            (H, W) float32 depth in metres, 0 where a ray meets no such surface.
        """
        h, w = (int(v) for v in size)
        if self.blocks_used == 0:
            return np.zeros((h, w), np.float32)
        fx, fy, cx, cy = (float(v) for v in intrinsics)
        K = o3c.Tensor(np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]), o3c.float64)
        E = o3c.Tensor(np.linalg.inv(np.asarray(pose, np.float64)), o3c.float64)
        hashmap = self.grid.hashmap()
        keys = hashmap.key_tensor()[hashmap.active_buf_indices().to(o3c.int64)].cpu().numpy()
        seen, tiles, near = blocks_in_view(keys, self.voxel * self.block_resolution, pose, intrinsics, (h, w),
                                           self.max_depth)
        depth = np.zeros((h, w), np.float32)
        order = np.argsort(near)  # each pass a shell of depth: few rays cross two of them
        keys, tiles = keys[seen][order], tiles[order]
        for part in tile_batches(tiles, RANGE_TILE_BUDGET):
            blocks = o3c.Tensor(np.ascontiguousarray(keys[part]), o3c.int32).to(self.device)
            # Open3D reports how it sized its range map on stdout; that is not the user's business.
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
                result = self.grid.ray_cast(blocks, K, E, w, h, ["depth"], 1.0, 0.05, self.max_depth,
                                            float(min_weight), self.trunc / self.voxel, RANGE_MAP_DOWN_FACTOR)
            found = result["depth"].cpu().numpy().reshape(h, w).astype(np.float32, copy=False)
            found = np.where(np.isfinite(found) & (found > 0), found, np.float32(0.0))
            # The nearest surface any pass found.
            depth = np.where((found > 0) & ((depth == 0) | (found < depth)), found, depth)
        return depth

    @property
    def blocks_used(self) -> int:
        """Voxel blocks allocated so far (the count at closing once the voxels are freed).

        Returns:
            Number of blocks.
        """
        return self._blocks_closed if self.grid is None else int(self.grid.hashmap().size())

    def close(self) -> None:
        """Free the voxels (their counts stay readable).

        Called once the mesh and points are out, before the decimation, which needs most of the
        memory the voxels held (+0.8 GB for 2.5 M triangles).
        """
        if self.grid is not None:
            self._blocks_closed = self.blocks_used
            self.grid = None
            from recon.memory import release_memory

            release_memory(force=True)

    def surface_curve(self) -> np.ndarray:
        """Estimated triangles marching cubes makes at each whole weight threshold, in one pass.

        Twice the voxel edges within a block whose two voxels have signed distances of
        opposite sign, counted by the lower of their two weights: each such edge is a vertex
        of the mesh, and a surface has about twice as many triangles as vertices (Euler).
        Edges across blocks are not counted (1/8 of them at block resolution 8).

        Returns:
            (K,) int64: entry k estimates the mesh of the voxels of weight >= k (entry 0 all
            observed voxels); empty when nothing is fused.
        """
        if self.blocks_used == 0:
            return np.zeros(0, np.int64)
        active = self.grid.hashmap().active_buf_indices().to(o3c.int64)
        tsdf, weight = self.grid.attribute("tsdf"), self.grid.attribute("weight")
        if self.device.get_type() == o3c.Device.DeviceType.CPU:  # numpy views: numpy's gather is ~30x Open3D's
            active, tsdf, weight = active.numpy(), tsdf.numpy(), weight.numpy()
        side = (-1,) + (self.block_resolution,) * 3
        edges = np.zeros(1, np.int64)
        for start in range(0, active.shape[0], _COUNT_CHUNK):
            part = active[start:start + _COUNT_CHUNK]
            negative = np.signbit(_host(tsdf[part]).reshape(side))
            observed = _host(weight[part]).reshape(side)
            for axis in (1, 2, 3):
                d, w = np.moveaxis(negative, axis, -1), np.moveaxis(observed, axis, -1)
                crossing = d[..., 1:] != d[..., :-1]
                lower = np.minimum(w[..., 1:][crossing], w[..., :-1][crossing])
                found = np.bincount(np.rint(lower).astype(np.int64))
                if len(found) > len(edges):
                    edges = np.pad(edges, (0, len(found) - len(edges)))
                edges[:len(found)] += found
        return 2 * np.cumsum(edges[::-1])[::-1]

    def surface_triangles(self, min_weight: float) -> int:
        """Estimated triangles marching cubes makes of the voxels of weight >= min_weight.

        Args:
            min_weight: observations a voxel needs (as Open3D tests it, weight > min_weight - 0.5).

        Returns:
            Estimated triangle count (surface_curve; 0 when nothing is fused).
        """
        return _at_weight(self.surface_curve(), min_weight)

    def bounded_weight(self, options) -> float:
        """The weight threshold the mesh is extracted at.

        options.meshing_weight, raised by whole observations while the surface
        (surface_curve) exceeds options.extraction_bound, so that extracting it stays within
        memory.

        Args:
            options: FusionOptions (weight_threshold, max_extracted, max_triangles).

        Returns:
            Observations a meshed voxel needs.
        """
        weight, ceiling = options.meshing_weight, options.extraction_bound
        if ceiling <= 0:
            return weight
        curve = self.surface_curve()
        while _at_weight(curve, weight) > ceiling:
            weight += 1.0
        return weight

    def mesh(self, options, weight: float | None = None) -> tuple[o3d.geometry.TriangleMesh, int]:
        """The mesh of what is fused so far, cleaned of small fragments.

        Vertex colours clipped to [0, 1] (TSDF colour averages can overshoot by rounding).

        Args:
            options: FusionOptions (weight_threshold, max_extracted, min_fragment_triangles,
                min_fragment_fraction).
            weight: observations a meshed voxel needs (None: bounded_weight(options)).

        Returns:
            (legacy TriangleMesh in world coordinates and canonical order, triangles removed
            as fragments).
        """
        # Open3D keeps voxels with weight > threshold; weights count observations (1 per frame).
        if self.blocks_used == 0:  # nothing integrated (Open3D raises on an empty hash map)
            return o3d.geometry.TriangleMesh(), 0
        threshold = (self.bounded_weight(options) if weight is None else weight) - 0.5
        mesh = _extract(lambda: self.grid.extract_triangle_mesh(threshold), o3d.geometry.TriangleMesh)
        mesh, removed = remove_fragments(mesh, options.min_fragment_triangles, options.min_fragment_fraction)
        if mesh.has_vertex_colors():
            mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(np.asarray(mesh.vertex_colors), 0, 1))
        return canonical_mesh(mesh), removed

    def point_cloud(self, options, weight: float | None = None) -> o3d.geometry.PointCloud:
        """The zero crossings of what is fused so far, at the mesh's weight threshold.

        Args:
            options: FusionOptions (weight_threshold, max_extracted).
            weight: observations a voxel needs (None: bounded_weight(options)).

        Returns:
            Legacy PointCloud in world coordinates, in canonical order (canonical_points).
        """
        if self.blocks_used == 0:
            return o3d.geometry.PointCloud()
        threshold = (self.bounded_weight(options) if weight is None else weight) - 0.5
        return canonical_points(_extract(lambda: self.grid.extract_point_cloud(threshold), o3d.geometry.PointCloud))


def _host(values) -> np.ndarray:
    """A numpy array of an Open3D tensor on any device (numpy arrays pass through)."""
    return values if isinstance(values, np.ndarray) else values.cpu().numpy()


def _at_weight(curve: np.ndarray, min_weight: float) -> int:
    """A surface_curve's entry for voxels of weight > min_weight - 0.5 (whole weights)."""
    index = max(0, math.floor(min_weight - 0.5) + 1)
    return int(curve[index]) if index < len(curve) else 0


# Open3D extracts vertices and points in the order of its hash map's buffer, which its
# parallel insertion makes differ between runs: the same surface came out as differently
# ordered files (and a fixed-seed surface sample of it as other points). Sorting by position
# gives the same bytes for the same volume.


def _position_order(points: np.ndarray) -> np.ndarray:
    """Indices sorting (M, 3) points by x, then y, then z."""
    return np.lexsort((points[:, 2], points[:, 1], points[:, 0]))


def canonical_points(cloud: o3d.geometry.PointCloud) -> o3d.geometry.PointCloud:
    """The point cloud (with its colours and normals) sorted by position.

    Args:
        cloud: legacy PointCloud.

    Returns:
        A new PointCloud sorted by x, then y, then z.
    """
    order = _position_order(np.asarray(cloud.points))
    out = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(cloud.points)[order]))
    if cloud.has_colors():
        out.colors = o3d.utility.Vector3dVector(np.asarray(cloud.colors)[order])
    if cloud.has_normals():
        out.normals = o3d.utility.Vector3dVector(np.asarray(cloud.normals)[order])
    return out


def canonical_mesh(mesh: o3d.geometry.TriangleMesh) -> o3d.geometry.TriangleMesh:
    """The same mesh with vertices sorted by position and triangles by their vertices.

    Each triangle is rotated to start at its lowest vertex, which keeps its winding.

    Args:
        mesh: legacy TriangleMesh (colours and normals carried along).

    Returns:
        A new TriangleMesh in canonical order.
    """
    vertices = np.asarray(mesh.vertices)
    order = _position_order(vertices)
    rank = np.empty(len(order), np.int32)
    rank[order] = np.arange(len(order), dtype=np.int32)
    triangles = rank[np.asarray(mesh.triangles)]
    if len(triangles):
        # Column by column (np.choose): whole-array index arithmetic would hold 64-bit copies.
        first, second, third = triangles.T
        start = np.argmin(triangles, axis=1)
        columns = [np.choose(start, turn) for turn in ((first, second, third), (second, third, first),
                                                       (third, first, second))]
        del first, second, third, triangles
        order_t = np.lexsort(columns[::-1])
        triangles = np.stack([column[order_t] for column in columns], axis=1)
    out = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices[order]),
                                    o3d.utility.Vector3iVector(triangles))
    if mesh.has_vertex_colors():
        out.vertex_colors = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_colors)[order])
    if mesh.has_vertex_normals():
        out.vertex_normals = o3d.utility.Vector3dVector(np.asarray(mesh.vertex_normals)[order])
    return out


__all__ = ["TsdfVolume", "canonical_mesh", "canonical_points", "clean_depth", "remove_fragments",
           "triangle_components"]
