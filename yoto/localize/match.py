"""Training-free contact localization: an exhaustive matched filter over the object surface and the sensor roll.

A GelSight contact is a small height map. Pressed at a point of the object along its normal, the sensor would
see the object's own height map there, up to the sensor's roll about the normal and a small tilt. So:

1. Once per object model, anchors every `anchor_spacing_m` on the parent cloud, each with a smoothed normal,
   a tangent frame and the object's height map over a disc of cells around it (rays cast on the mesh).
2. Per contact, the tactile cloud becomes a height image in its own tangent frame, sampled at the same
   cells for every roll. The squared height difference after removing the best plane (offset and tilt),
   for every (roll, anchor), is a handful of matrix products: a coarse pass over every anchor, then a fine
   pass over the best `shortlist`. Cells where the sensor saw nothing but the anchor's surface would have
   pushed into the gel count against the anchor (free space).
3. The best anchors after non-maximum suppression give full sensor poses on the object; each is refined by
   a damped point-to-plane ICP of the tactile points and ranked by its truncated residual (plus free-space
   violation). Beliefs come from those residuals.

No training, nothing learnt: it works on any object model the moment it is built. A contact on a featureless
region (a flat face, a cylinder) matches many places equally well; the candidates then carry that ambiguity to
the pose stage, whose joint two-contact selection resolves what geometry allows.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from yoto.contacts import validate_tactile_points
from yoto.errors import DegenerateGeometryError, InputError, require_open3d
from yoto.geometry import make_transform, normalize, rotation_about_axis
from yoto.objects.model import ObjectModel
from yoto.sensor.spec import GELSIGHT_MINI
from yoto.solver import ContactEstimate, contact_in_sensor

Z_AXIS = np.array([0.0, 0.0, 1.0])
MIN_CONTACT_CELLS = 3  # fewer covered cells leave nothing to match


@dataclass(frozen=True)
class MatchConfig:
    """The matched-filter localizer."""

    anchor_spacing_m: float = 0.002  # anchors: one parent point per voxel of this size
    anchor_normal_neighbours: int = 50  # k of an anchor's aggregated normal (smooth, stable)
    map_radius_m: float = 0.0105  # height maps cover the disc of this radius around the contact / anchor
    cell_m: float = 0.0015  # height-map cell size
    rolls: int = 36  # sensor roll angles tried by the fine stage (360 / rolls degrees apart)
    coarse_rolls: int = 24  # roll angles of the coarse stage, which scores every anchor on half the cells
    shortlist: int = 1500  # anchors (best by the coarse stage) scored by the fine stage
    ray_start_m: float = 0.005  # anchor rays start this far in front of the tangent plane
    ray_reach_m: float = 0.005  # surface further than this behind the tangent plane counts as absent
    air_penalty_m: float = 0.0005  # a contact cell with no anchor surface costs like this height error
    remove_tilt: bool = True  # fit and remove a plane (offset + tilt) instead of a constant offset
    contact_pixel_m: float = 0.0002  # pixel of the contact's local height image
    contact_erode_px: int = 1  # the contact image's mask is eroded by this many pixels (the rim is gel, not object)
    free_margin_m: float = 0.0001  # free space: the object may reach this far past the gel plane unseen ...
    free_margin_quantile: float = 0.02  # ... or as deep as the cloud's shallowest points (this quantile of depth)
    free_clearance_m: float = 0.0005  # free space: cells this close to the contact are not judged
    pad_size_m: tuple[float, float] = GELSIGHT_MINI.pad_size_m  # sensed area of the gel (x, y extents)
    nms_radius_m: float = 0.004  # matched-filter candidates closer than this are one
    refine_candidates: int = 20  # best matched-filter candidates refined by ICP
    icp_points: int = 300  # tactile points used by the per-candidate ICP
    icp_iterations: int = 8  # Gauss-Newton iterations of the per-candidate ICP
    icp_max_distance_m: float = 0.002  # correspondences further than this are ignored by ICP
    residual_tau_m: float = 0.0005  # truncation of the ranking residual
    prior_rotation_rad: float = float(np.radians(10.0))  # weak prior of the ICP on its start: rotation ...
    prior_translation_m: float = 0.003  # ... and translation
    surface_noise_m: float = 0.00003  # tactile noise scale of the ICP weights
    temperature_m: float = 1e-4  # belief: exp(-(residual / T)^2 / 2)
    null_residual_m: float = 3e-4  # residual of the "none of these" hypothesis
    dedup_radius_m: float = 0.003  # refined candidates whose contacts lie closer than this are one
    num_candidates: int = 10  # candidates returned
    normal_neighbours: int = 20  # k of the aggregated model normal reported with a candidate
    free_space: bool = True  # penalise poses that push the object into the gel where the sensor saw nothing
    refine: bool = True  # refine the candidates by ICP (False: matched-filter poses only)

    def __post_init__(self):
        if self.rolls < 1 or self.num_candidates < 1 or self.refine_candidates < 1:
            raise InputError("rolls, num_candidates and refine_candidates must be at least 1")
        if self.cell_m <= 0 or self.map_radius_m <= self.cell_m or self.anchor_spacing_m <= 0:
            raise InputError("cell_m and anchor_spacing_m must be positive and map_radius_m larger than a cell")


# ------------------------------------------------------------------------------------------------ grid
@dataclass(frozen=True)
class MapGrid:
    """Cells of a height map: squares of `cell_m` whose centres lie within a disc of `radius_m`."""

    cell_m: float
    radius_m: float

    @property
    def centres(self) -> np.ndarray:
        """(C, 2) cell centres (x, y), row by row."""
        side = 2 * int(np.ceil(self.radius_m / self.cell_m))
        coords = (np.arange(side) + 0.5 - side / 2.0) * self.cell_m
        cx, cy = np.meshgrid(coords, coords, indexing="ij")
        inside = cx**2 + cy**2 <= self.radius_m**2
        return np.stack([cx[inside], cy[inside]], axis=1)

    @property
    def size(self) -> int:
        return len(self.centres)

    @property
    def coarse(self) -> np.ndarray:
        """(C,) bool: the checkerboard half of the cells (a lattice sqrt(2) cells apart), for the coarse stage."""
        side = 2 * int(np.ceil(self.radius_m / self.cell_m))
        index = np.rint(self.centres / self.cell_m + side / 2.0 - 0.5).astype(np.int64)
        return (index.sum(axis=1) % 2) == 0


def tangent_bases(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A fixed tangent basis (u, v) per unit normal n, with (u, v, -n) right-handed."""
    helper = np.eye(3)[np.argmin(np.abs(normals), axis=1)]
    u = normalize(np.cross(helper, normals))
    v = np.cross(-normals, u)
    return u, v


# ------------------------------------------------------------------------------------------------ anchors
@dataclass
class AnchorMaps:
    """Anchors on the object surface and the height map a sensor pressed at each would see."""

    points_object: np.ndarray  # (A, 3) anchor locations (parent points)
    normals_object: np.ndarray  # (A, 3) outward unit normals
    u_object: np.ndarray  # (A, 3) tangent axis u
    v_object: np.ndarray  # (A, 3) tangent axis v; (u, v, -n) is right-handed
    heights: np.ndarray  # (A, C) float32 surface height into the object along -n at each cell centre (0: invalid)
    valid: np.ndarray  # (A, C) float32 1 where the anchor has surface at the cell centre
    grid: MapGrid
    neighbours: list[np.ndarray]  # per anchor, the anchors within the NMS radius
    seconds: float  # time to build

    def __post_init__(self):
        # (C, A) contiguous right-hand sides of the matched filter's matrix products
        self.valid_columns = np.ascontiguousarray(self.valid.T, dtype=np.float32)
        self.height_columns = np.ascontiguousarray(self.heights.T, dtype=np.float32)
        self.height2_columns = self.height_columns * self.height_columns
        coarse = self.grid.coarse
        self.coarse_columns = tuple(np.ascontiguousarray(a[coarse]) for a in (self.valid_columns, self.height_columns))


def mesh_scene(model: ObjectModel):
    o3d = require_open3d("the matched-filter localizer")
    mesh = model.mesh_object
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)),
    )
    return scene


def cast_height_maps(
    scene,
    anchors: np.ndarray,
    normals: np.ndarray,
    u: np.ndarray,
    v: np.ndarray,
    grid: MapGrid,
    config: MatchConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """(A, C) surface heights at the cell centres of each anchor frame, by casting rays along -n onto the mesh.

    A ray starts `ray_start_m` in front of the tangent plane. Its first hit is the surface a sensor pressed
    along -n would meet; a back-face hit means the ray started inside the object (the surface rises above the
    start): height -ray_start_m. No hit, or a hit deeper than `ray_reach_m`: no surface (invalid).
    """
    o3d = require_open3d("the matched-filter localizer")
    centres = grid.centres
    heights = np.zeros((len(anchors), grid.size), dtype=np.float32)
    valid = np.zeros((len(anchors), grid.size), dtype=np.float32)
    chunk = max(1, 1_000_000 // grid.size)
    for first in range(0, len(anchors), chunk):
        last = min(first + chunk, len(anchors))
        count = (last - first) * grid.size
        origins = (
            anchors[first:last, None, :]
            + centres[None, :, 0, None] * u[first:last, None, :]
            + centres[None, :, 1, None] * v[first:last, None, :]
            + config.ray_start_m * normals[first:last, None, :]
        ).reshape(count, 3)
        directions = np.broadcast_to(-normals[first:last, None, :], (last - first, grid.size, 3)).reshape(count, 3)
        hits = scene.cast_rays(o3d.core.Tensor(np.concatenate([origins, directions], axis=1).astype(np.float32)))
        t_hit = hits["t_hit"].numpy().astype(np.float64)
        back = np.einsum("ij,ij->i", hits["primitive_normals"].numpy(), directions) > 0.0
        h = np.where(back, -config.ray_start_m, t_hit - config.ray_start_m)
        ok = np.isfinite(t_hit) & (h <= config.ray_reach_m)
        heights[first:last] = np.where(ok, h, 0.0).reshape(last - first, grid.size)
        valid[first:last] = ok.reshape(last - first, grid.size)
    return heights, valid


def build_anchor_maps(model: ObjectModel, config: MatchConfig) -> AnchorMaps:
    """Anchors every `anchor_spacing_m` on the parent cloud with their height maps (once per object model)."""
    from yoto.pointcloud import voxel_downsample

    start = time.perf_counter()
    points = model.points_object.astype(np.float64)
    (centres,) = voxel_downsample(points, config.anchor_spacing_m)
    _, nearest = model.kdtree.query(centres)
    anchors = points[np.unique(nearest)]
    normals = model.aggregated_normal(anchors, config.anchor_normal_neighbours)
    u, v = tangent_bases(normals)
    grid = MapGrid(config.cell_m, config.map_radius_m)
    heights, valid = cast_height_maps(mesh_scene(model), anchors, normals, u, v, grid, config)
    neighbours = [
        np.asarray(n, dtype=np.int64) for n in cKDTree(anchors).query_ball_point(anchors, config.nms_radius_m)
    ]
    return AnchorMaps(anchors, normals, u, v, heights, valid, grid, neighbours, time.perf_counter() - start)


_CACHE: dict[tuple[str, MatchConfig], AnchorMaps] = {}
_CACHE_LOCK = threading.Lock()
_CACHE_SIZE = 4


def anchor_maps(model: ObjectModel, config: MatchConfig) -> AnchorMaps:
    """The cached anchor maps of a model (keyed by its fingerprint and the map settings)."""
    key = (model.fingerprint, config)
    with _CACHE_LOCK:
        cached = _CACHE.get(key)
    if cached is None:
        cached = build_anchor_maps(model, config)
        with _CACHE_LOCK:
            if len(_CACHE) >= _CACHE_SIZE:
                _CACHE.pop(next(iter(_CACHE)))
            _CACHE[key] = cached
    return cached


def clear_cache() -> None:
    with _CACHE_LOCK:
        _CACHE.clear()


# ------------------------------------------------------------------------------------------------ contact
@dataclass
class ContactImage:
    """The tactile cloud as a height image in its local frame (x, y tangent; t = height into the object)."""

    centre_sensor: np.ndarray  # (3,) contact centre
    normal_sensor: np.ndarray  # (3,) outward normal
    basis_sensor: np.ndarray  # (3, 3) columns u, v, z' (= -normal) of the local frame
    heights: np.ndarray  # (S, S) mean height per pixel
    filled: np.ndarray  # (S, S) pixels holding points
    mask: np.ndarray  # (S, S) pixels trusted as object surface (filled, rim eroded)
    touched: np.ndarray  # (S, S) pixels within the free-space clearance of the contact
    pixel_m: float
    half_m: float  # the image spans [-half, half] in x and y
    free_margin_m: float  # unseen surface may press the gel this deep without contradicting the contact

    def sample(self, x: np.ndarray, y: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Bilinear heights at local (x, y) and whether all four pixels are in `mask`."""
        side = len(self.heights)
        fx = (x + self.half_m) / self.pixel_m - 0.5
        fy = (y + self.half_m) / self.pixel_m - 0.5
        x0 = np.clip(np.floor(fx).astype(np.int64), 0, side - 2)
        y0 = np.clip(np.floor(fy).astype(np.int64), 0, side - 2)
        wx = np.clip(fx - x0, 0.0, 1.0)
        wy = np.clip(fy - y0, 0.0, 1.0)
        corners = (
            (x0, y0, (1 - wx) * (1 - wy)),
            (x0 + 1, y0, wx * (1 - wy)),
            (x0, y0 + 1, (1 - wx) * wy),
            (x0 + 1, y0 + 1, wx * wy),
        )
        heights = sum(self.heights[i, j] * w for i, j, w in corners)
        inside = np.logical_and.reduce([mask[i, j] for i, j, _ in corners])
        return heights, inside

    def points_local(self) -> np.ndarray:
        """(M, 3) pixel centres of the trusted mask with their heights, local frame."""
        i, j = np.nonzero(self.mask)
        return np.stack(
            [(i + 0.5) * self.pixel_m - self.half_m, (j + 0.5) * self.pixel_m - self.half_m, self.heights[i, j]], axis=1
        )

    def to_sensor(self, local: np.ndarray) -> np.ndarray:
        return self.centre_sensor + local @ self.basis_sensor.T


def tactile_spacing_m(local: np.ndarray, samples: int = 512) -> float:
    """Median in-plane distance between neighbouring tactile points (the cloud's own resolution)."""
    step = max(1, len(local) // samples)
    distances, _ = cKDTree(local[:, :2]).query(local[::step, :2], k=2)
    return float(np.median(distances[:, 1]))


def contact_image(points_sensor: np.ndarray, radius_m: float, config: MatchConfig) -> ContactImage:
    """The tactile cloud as a height image around its contact centre.

    Pixels are `contact_pixel_m`, or coarser when the cloud is sparser than that (clouds from other programs
    may be); single empty pixels inside the contact are filled from their neighbours, so sparse sampling
    does not punch holes that the rim erosion would widen.
    """
    centre, normal = contact_in_sensor(points_sensor)
    z_local = -normal
    x_axis = np.array([1.0, 0.0, 0.0])
    u = normalize(x_axis - (x_axis @ z_local) * z_local)
    basis = np.stack([u, np.cross(z_local, u), z_local], axis=1)
    local = (points_sensor - centre) @ basis
    pixel = max(config.contact_pixel_m, 1.5 * tactile_spacing_m(local))
    half = radius_m + 2.0 * pixel
    side = int(np.ceil(2.0 * half / pixel))
    ix = np.floor((local[:, 0] + half) / pixel).astype(np.int64)
    iy = np.floor((local[:, 1] + half) / pixel).astype(np.int64)
    inside = (ix >= 0) & (ix < side) & (iy >= 0) & (iy < side)
    if not inside.any():
        raise DegenerateGeometryError("the tactile cloud has no points around its contact centre")
    key = ix[inside] * side + iy[inside]
    sums = np.bincount(key, weights=local[inside, 2], minlength=side * side).reshape(side, side)
    counts = np.bincount(key, minlength=side * side).reshape(side, side).astype(np.float64)
    filled = counts > 0
    holes = ndimage.binary_closing(filled) & ~filled
    if holes.any():
        # a hole's height: the mean of the points in its 3 x 3 neighbourhood
        sums = np.where(holes, ndimage.uniform_filter(sums, 3, mode="constant"), sums)
        counts = np.where(holes, ndimage.uniform_filter(counts, 3, mode="constant"), counts)
        filled = filled | holes
    heights = np.where(filled, sums / np.maximum(counts, 1e-12), 0.0)
    mask = filled
    if config.contact_erode_px > 0:
        mask = ndimage.binary_erosion(filled, iterations=config.contact_erode_px)
    clearance = int(np.ceil(config.free_clearance_m / pixel))
    touched = ndimage.binary_dilation(filled, iterations=clearance) if clearance > 0 else filled
    # A sensor may report only the deeper part of a contact (a reconstruction's mask keeps pixels pressed at
    # least some fraction of the deepest): surface pressing the gel less deep than the cloud's shallowest
    # points may lie where nothing was reported.
    shallowest = float(np.quantile(-points_sensor[:, 2], config.free_margin_quantile))
    free_margin = max(config.free_margin_m, shallowest + config.free_margin_m)
    return ContactImage(centre, normal, basis, heights, filled, mask, touched, pixel, half, free_margin)


@dataclass
class ContactMaps:
    """The contact's height map at every roll, sampled at the grid's cell centres (anchor-frame coordinates)."""

    image: ContactImage
    heights: np.ndarray  # (R, C) float32 contact height at each cell centre (0 where not covered)
    mask: np.ndarray  # (R, C) float32 1 where the contact covers the cell centre
    free: np.ndarray  # (R, C) bool: cells on the pad, away from the contact (the object did not touch there)
    gel_heights: np.ndarray  # (R, C) height of the undeformed gel plane (z_sensor = 0) at each cell
    rolls_rad: np.ndarray  # (R,)


def contact_maps(image: ContactImage, centres: np.ndarray, rolls: int, config: MatchConfig) -> ContactMaps:
    """Sample the contact image at the cell centres (C, 2) of every roll: anchor local = Rz(roll) contact local."""
    rolls = np.arange(rolls) * (2.0 * np.pi / rolls)
    cos, sin = np.cos(rolls)[:, None], np.sin(rolls)[:, None]
    x = cos * centres[:, 0] + sin * centres[:, 1]  # Rz(-roll) applied to the cell centres
    y = -sin * centres[:, 0] + cos * centres[:, 1]
    heights, covered = image.sample(x, y, image.mask)
    _, near = image.sample(x, y, ~image.touched)
    basis, centre = image.basis_sensor, image.centre_sensor
    on_pad = centre[:2, None, None] + basis[:2, 0, None, None] * x + basis[:2, 1, None, None] * y
    pad = np.asarray(config.pad_size_m) / 2.0
    free = (np.abs(on_pad[0]) <= pad[0]) & (np.abs(on_pad[1]) <= pad[1]) & near
    gel = -(centre[2] + basis[2, 0] * x + basis[2, 1] * y) / basis[2, 2]
    return ContactMaps(
        image=image,
        heights=np.where(covered, heights, 0.0).astype(np.float32),
        mask=covered.astype(np.float32),
        free=free,
        gel_heights=gel.astype(np.float32),
        rolls_rad=rolls,
    )


# ------------------------------------------------------------------------------------------------ scores
def plane_costs(
    mt: np.ndarray,
    t: np.ndarray,
    ma: np.ndarray,
    h: np.ndarray,
    hh: np.ndarray,
    centres: np.ndarray,
    remove_tilt: bool,
    air_penalty_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Cost (R, A) of every (roll, anchor) and the fitted plane beta = (offset, slope x, slope y), (3, R, A).

    Inputs: the contact's mask and heights (R, C) at the cell centres (C, 2) for each roll, and the anchors'
    validity, heights and squared heights as (C, A) columns (heights 0 where invalid). With d = t - h over the
    cells both cover, cost = (min_beta sum (d - beta . (1, x, y))^2 + air_penalty^2 * contact cells where the
    anchor has no surface) / contact cells; without `remove_tilt` beta is the offset alone. Every sum over
    cells is one matrix product of (rolls x cells) contact terms with (cells x anchors) anchor terms.
    """
    x, y = centres.T.astype(np.float32)
    mtt = mt * t
    total = mt.sum(axis=1, keepdims=True)
    if remove_tilt:
        first = np.concatenate([mt, mt * x, mt * y, mt * x * x, mt * x * y, mt * y * y, mtt, mtt * x, mtt * y, mtt * t])
        n, sx, sy, sxx, sxy, syy, st, stx, sty, stt = np.split(first @ ma, 10)
        sh, shx, shy, sth = np.split(np.concatenate([mt, mt * x, mt * y, mtt]) @ h, 4)
        b0, b1, b2 = st - sh, stx - shx, sty - shy
        sdd = stt - 2.0 * sth + mt @ hh
        # Normal equations G beta = b, G = [[n, sx, sy], [sx, sxx, sxy], [sy, sxy, syy]], solved by cofactors.
        c00, c01, c02 = sxx * syy - sxy * sxy, sy * sxy - sx * syy, sx * sxy - sy * sxx
        c11, c12, c22 = n * syy - sy * sy, sx * sy - n * sxy, n * sxx - sx * sx
        det = n * c00 + sx * c01 + sy * c02
        spread = sxx + syy
        # A plane needs cells spread in two directions: det is ~ n * (second moments)^2 when it is well posed.
        solvable = (n >= 6) & (det > 1e-2 * n * spread * spread / 4.0)
        inv = np.where(solvable, 1.0 / np.where(solvable, det, 1.0), 0.0)
        beta = np.stack(
            [
                (c00 * b0 + c01 * b1 + c02 * b2) * inv,
                (c01 * b0 + c11 * b1 + c12 * b2) * inv,
                (c02 * b0 + c12 * b1 + c22 * b2) * inv,
            ]
        )
        safe_n = np.maximum(n, 1.0)
        sse = np.where(solvable, sdd - (beta[0] * b0 + beta[1] * b1 + beta[2] * b2), sdd - b0 * b0 / safe_n)
        beta[0] = np.where(solvable, beta[0], b0 / safe_n)
    else:
        n, st, stt = np.split(np.concatenate([mt, mtt, mtt * t]) @ ma, 3)
        sh, sth = np.split(np.concatenate([mt, mtt]) @ h, 2)
        safe_n = np.maximum(n, 1.0)
        sse = stt - 2.0 * sth + mt @ hh - (st - sh) ** 2 / safe_n
        beta = np.zeros((3,) + n.shape, dtype=np.float32)
        beta[0] = (st - sh) / safe_n
    cost = (np.maximum(sse, 0.0) + air_penalty_m**2 * (total - n)) / np.maximum(total, 1.0)
    return cost, beta


def free_space_penalty(
    contact: ContactMaps,
    anchors: AnchorMaps,
    anchor_index: np.ndarray,
    roll_index: np.ndarray,
    beta: np.ndarray,
    config: MatchConfig,
) -> np.ndarray:
    """(K,) sum over free pad cells of the squared depth by which the anchor's surface would push into the gel.

    Under a hypothesis the contact-frame height of the anchor's surface at a cell is h + beta . (1, x, y); the
    gel plane lies at `gel_heights`. Surface nearer the sensor than the plane (less a margin) on a cell where
    the sensor saw no contact contradicts the hypothesis.
    """
    x, y = anchors.grid.centres.T
    h = anchors.heights[anchor_index].astype(np.float64)
    surface = h + beta[0][:, None] + beta[1][:, None] * x + beta[2][:, None] * y
    depth = np.minimum(contact.gel_heights[roll_index] - contact.image.free_margin_m - surface, config.ray_start_m)
    judged = contact.free[roll_index] & (anchors.valid[anchor_index] > 0)
    return np.sum(np.where(judged, np.maximum(depth, 0.0) ** 2, 0.0), axis=1)


# ------------------------------------------------------------------------------------------------ refinement
def _rotation_vectors_to_matrices(omega: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(omega, axis=1)
    axis = omega / np.maximum(angle, 1e-12)[:, None]
    k = np.zeros((len(omega), 3, 3))
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k[:, 1, 0], k[:, 2, 0], k[:, 2, 1] = axis[:, 2], -axis[:, 1], axis[:, 0]
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def refine_poses(
    model: ObjectModel,
    points_sensor: np.ndarray,
    normal_sensor: np.ndarray,
    centre_sensor: np.ndarray,
    T_object_sensor: np.ndarray,
    config: MatchConfig,
) -> np.ndarray:
    """(K, 4, 4) poses after a damped point-to-plane Gauss-Newton of the tactile points on the parent cloud.

    All K candidates at once: one KD-tree query per iteration for all of them. The update rotates about each
    candidate's contact centre (not the object origin, which would couple rotation and translation); the
    start is a weak Gaussian prior, so directions the surface does not constrain (sliding on a plane, spinning
    on a sphere) stay where the matched filter put them.
    """
    poses = np.array(T_object_sensor, dtype=np.float64)
    start = poses.copy()
    k, m = len(poses), len(points_sensor)
    prior = np.diag([1.0 / config.prior_rotation_rad**2] * 3 + [1.0 / config.prior_translation_m**2] * 3)
    parent_points = model.points_object
    parent_normals = model.normals_object
    for _ in range(config.icp_iterations):
        rotation, translation = poses[:, :3, :3], poses[:, :3, 3]
        p = points_sensor @ np.transpose(rotation, (0, 2, 1)) + translation[:, None, :]
        centres = rotation @ centre_sensor + translation
        distances, index = model.kdtree.query(p.reshape(-1, 3), distance_upper_bound=config.icp_max_distance_m)
        found = np.isfinite(distances).reshape(k, m)
        index = np.where(found.ravel(), index, 0)
        q = parent_points[index].reshape(k, m, 3).astype(np.float64)
        n = parent_normals[index].reshape(k, m, 3).astype(np.float64)
        facing = (n @ (rotation @ normal_sensor)[:, :, None])[:, :, 0] > 0.5
        use = found & facing
        r = np.sum((p - q) * n, axis=2)
        scale = np.maximum(config.surface_noise_m, 1.4826 * np.median(np.where(use, np.abs(r), np.nan), axis=1))
        scale = np.where(np.isfinite(scale), scale, config.surface_noise_m)
        weights = np.where(use, np.minimum(1.0, scale[:, None] / np.maximum(np.abs(r), 1e-12)), 0.0)
        weights /= config.surface_noise_m**2
        jacobian = np.concatenate([np.cross(p - centres[:, None, :], n), n], axis=2)  # (K, M, 6)
        # deviation from the start, in the update's coordinates (rotation about the current contact centre)
        relative = poses[:, :3, :3] @ np.transpose(start[:, :3, :3], (0, 2, 1))
        angle = np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0))
        axis = np.stack(
            [
                relative[:, 2, 1] - relative[:, 1, 2],
                relative[:, 0, 2] - relative[:, 2, 0],
                relative[:, 1, 0] - relative[:, 0, 1],
            ],
            axis=1,
        )
        rotvec = axis * np.where(angle < 1e-9, 0.5, angle / (2.0 * np.sin(np.maximum(angle, 1e-9))))[:, None]
        start_centres = start[:, :3, :3] @ centre_sensor + start[:, :3, 3]
        deviation = np.concatenate([rotvec, centres - start_centres], axis=1)
        weighted = jacobian * weights[:, :, None]
        hessian = np.transpose(weighted, (0, 2, 1)) @ jacobian + prior
        gradient = (np.transpose(weighted, (0, 2, 1)) @ r[:, :, None])[:, :, 0] + deviation @ prior
        step = -np.linalg.solve(hessian, gradient[:, :, None])[:, :, 0]
        delta = _rotation_vectors_to_matrices(step[:, :3])
        # p -> delta (p - c) + c + tau
        new_rotation = delta @ rotation
        new_translation = (delta @ (translation - centres)[:, :, None])[:, :, 0] + centres + step[:, 3:]
        poses[:, :3, :3], poses[:, :3, 3] = new_rotation, new_translation
        if np.abs(step).max() < 1e-7:
            break
    return poses


def fit_residuals(
    model: ObjectModel, points_sensor: np.ndarray, normal_sensor: np.ndarray, T_object_sensor: np.ndarray, tau_m: float
) -> np.ndarray:
    """(K,) truncated RMS point-to-plane residual of the tactile points under each pose."""
    k, m = len(T_object_sensor), len(points_sensor)
    rotation, translation = T_object_sensor[:, :3, :3], T_object_sensor[:, :3, 3]
    p = points_sensor @ np.transpose(rotation, (0, 2, 1)) + translation[:, None, :]
    # Search further than tau: the nearest parent point can lie a point spacing away from a point on the surface.
    reach = tau_m + 3.0 * model.point_spacing_m
    distances, index = model.kdtree.query(p.reshape(-1, 3), distance_upper_bound=reach)
    found = np.isfinite(distances).reshape(k, m)
    index = np.where(found.ravel(), index, 0)
    q = model.points_object[index].reshape(k, m, 3)
    n = model.normals_object[index].reshape(k, m, 3).astype(np.float64)
    facing = (n @ (rotation @ normal_sensor)[:, :, None])[:, :, 0] > 0.5
    plane = np.abs(np.sum((p - q) * n, axis=2))
    residual = np.where(found & facing, np.minimum(plane, tau_m), tau_m)
    return np.sqrt(np.mean(residual**2, axis=1))


def free_space_violation(
    model: ObjectModel, image: ContactImage, T_object_sensor: np.ndarray, config: MatchConfig
) -> np.ndarray:
    """(K,) mean squared depth (capped at tau) by which the object would push into the gel unseen, per tactile sample.

    Parent points near the sensor are mapped into the sensor frame; those over the pad, beyond the gel
    plane by more than the margin, and not near the observed contact, each contribute their depth squared,
    weighted by the area they represent relative to a tactile sample's.
    """
    pad = np.asarray(config.pad_size_m) / 2.0
    reach = float(np.hypot(*pad)) + 0.002
    tactile_samples = max(int(image.mask.sum()), 1)
    sample_area = image.pixel_m**2
    point_area = model.point_spacing_m**2
    members = model.kdtree.query_ball_point(T_object_sensor[:, :3, 3], reach)
    counts = np.array([len(m) for m in members])
    if counts.sum() == 0:
        return np.zeros(len(T_object_sensor))
    owner = np.repeat(np.arange(len(T_object_sensor)), counts)
    p_object = model.points_object[np.concatenate([np.asarray(m, dtype=np.int64) for m in members])].astype(np.float64)
    offsets = p_object - T_object_sensor[owner, :3, 3]
    p_sensor = np.einsum("ni,nij->nj", offsets, T_object_sensor[owner, :3, :3])
    depth = -p_sensor[:, 2] - image.free_margin_m
    over = (np.abs(p_sensor[:, 0]) <= pad[0]) & (np.abs(p_sensor[:, 1]) <= pad[1]) & (depth > 0)
    local = (p_sensor[over] - image.centre_sensor) @ image.basis_sensor
    _, away = image.sample(local[:, 0], local[:, 1], ~image.touched)
    depth = np.minimum(depth[over][away], config.residual_tau_m)
    violation = np.bincount(owner[over][away], weights=depth**2, minlength=len(T_object_sensor))
    return violation * point_area / sample_area / tactile_samples


# ------------------------------------------------------------------------------------------------ localizer
class MatchLocalizer:
    """Locates a tactile contact by matching its height map against every anchor and roll (no training)."""

    name = "match"
    needs_ground_truth = False

    def __init__(self, config: MatchConfig = MatchConfig()):
        self.config = config

    def prepare_object(self, model: ObjectModel) -> AnchorMaps:
        return anchor_maps(model, self.config)

    def hypotheses(self, points_sensor: np.ndarray, model: ObjectModel) -> dict:
        """The matched filter's shortlist: anchors, rolls, costs and poses (best first, NMS applied)."""
        config = self.config
        anchors = anchor_maps(model, config)
        grid = anchors.grid
        image = contact_image(points_sensor, grid.radius_m, config)
        # Coarse stage: every anchor, half the cells, fewer rolls, offset only.
        coarse = grid.coarse
        contact = contact_maps(image, grid.centres[coarse], config.coarse_rolls, config)
        if contact.mask.sum(axis=1).max() < MIN_CONTACT_CELLS:
            raise DegenerateGeometryError(
                f"the tactile contact covers fewer than {MIN_CONTACT_CELLS} height-map cells "
                f"({config.cell_m * 1000:.2f} mm apart): too small to match (is the cloud in metres?)"
            )
        valid_coarse, height_coarse = anchors.coarse_columns
        cost, _ = plane_costs(
            contact.mask,
            contact.heights,
            valid_coarse,
            height_coarse,
            height_coarse * height_coarse,
            grid.centres[coarse],
            False,
            config.air_penalty_m,
        )
        best = cost.min(axis=0)
        count = min(config.shortlist, len(best))
        shortlist = np.argpartition(best, count - 1)[:count] if count < len(best) else np.arange(len(best))
        shortlist = np.sort(shortlist)
        # Fine stage: the shortlist, every cell, every roll, offset and tilt, free space.
        contact = contact_maps(image, grid.centres, config.rolls, config)
        cost, beta = plane_costs(
            contact.mask,
            contact.heights,
            anchors.valid_columns[:, shortlist],
            anchors.height_columns[:, shortlist],
            anchors.height2_columns[:, shortlist],
            grid.centres,
            config.remove_tilt,
            config.air_penalty_m,
        )
        best_roll = np.argmin(cost, axis=0)
        columns = np.arange(len(shortlist))
        score = cost[best_roll, columns].astype(np.float64)
        beta = beta[:, best_roll, columns]
        if config.free_space:
            penalty = free_space_penalty(contact, anchors, shortlist, best_roll, beta, config)
            score = score + penalty / np.maximum(contact.mask.sum(axis=1)[best_roll], 1.0)
        suppressed = np.zeros(len(best), dtype=bool)
        kept: list[int] = []
        for i in np.argsort(score, kind="stable"):
            a = shortlist[i]
            if suppressed[a]:
                continue
            kept.append(int(i))
            suppressed[anchors.neighbours[a]] = True
            if len(kept) >= config.refine_candidates:
                break
        poses = np.array(
            [self._pose(image, anchors, shortlist[i], contact.rolls_rad[best_roll[i]], beta[:, i]) for i in kept]
        )
        return {
            "image": image,
            "anchors": shortlist[kept],
            "rolls": best_roll[kept],
            "filter_cost": score[kept],
            "poses": poses,
        }

    @staticmethod
    def _pose(image: ContactImage, anchors: AnchorMaps, a: int, roll: float, beta: np.ndarray) -> np.ndarray:
        """T_object_sensor of a hypothesis: contact local -> (tilt, roll) -> anchor local -> object."""
        frame_anchor = np.stack([anchors.u_object[a], anchors.v_object[a], -anchors.normals_object[a]], axis=1)
        spin = rotation_about_axis(Z_AXIS, roll)
        tilt = np.array([-beta[2], beta[1], 0.0], dtype=np.float64)
        angle = float(np.linalg.norm(tilt))
        if angle > 1e-9:
            spin = rotation_about_axis(tilt, angle) @ spin
        rotation = frame_anchor @ spin @ image.basis_sensor.T
        origin = anchors.points_object[a] + float(beta[0]) * anchors.normals_object[a]
        return make_transform(rotation, origin - rotation @ image.centre_sensor)

    def localize(
        self, points_sensor: np.ndarray, model: ObjectModel, truth_p_object: np.ndarray | None = None
    ) -> list[ContactEstimate]:
        config = self.config
        points_sensor = validate_tactile_points(points_sensor, None)
        found = self.hypotheses(points_sensor, model)
        image: ContactImage = found["image"]
        local = image.points_local()
        if len(local) > config.icp_points:
            local = local[np.linspace(0, len(local) - 1, config.icp_points).astype(np.int64)]
        samples = image.to_sensor(local)
        poses = found["poses"]
        if config.refine:
            poses = refine_poses(model, samples, image.normal_sensor, image.centre_sensor, poses, config)
        residual = fit_residuals(model, samples, image.normal_sensor, poses, config.residual_tau_m)
        violation = free_space_violation(model, image, poses, config) if config.free_space else np.zeros(len(poses))
        total = np.sqrt(residual**2 + violation)
        order = np.argsort(total, kind="stable")
        centres = np.einsum("kij,j->ki", poses[:, :3, :3], image.centre_sensor) + poses[:, :3, 3]
        p_all = model.nearest_surface_point(centres)
        kept: list[int] = []
        for i in order:
            if all(np.linalg.norm(p_all[i] - p_all[j]) >= config.dedup_radius_m for j in kept):
                kept.append(int(i))
        residuals = np.append(total[kept], config.null_residual_m)
        exponents = -0.5 * (residuals / config.temperature_m) ** 2
        weights = np.exp(exponents - exponents.max())
        probabilities = weights[:-1] / weights.sum()
        out = []
        for i, probability in zip(kept[: config.num_candidates], probabilities, strict=False):
            p = p_all[i]
            out.append(
                ContactEstimate(
                    p_object=p,
                    n_object=model.aggregated_normal(p, config.normal_neighbours),
                    block=int(model.block_of_points(p)[0]),
                    score=float(1.0 - min(total[i], config.residual_tau_m) / config.residual_tau_m),
                    probability=float(probability),
                    details={
                        "match_anchor": int(found["anchors"][i]),
                        "match_roll_deg": float(np.degrees(2.0 * np.pi * found["rolls"][i] / config.rolls)),
                        "match_filter_rms_mm": 1000.0 * float(np.sqrt(max(found["filter_cost"][i], 0.0))),
                        "match_residual_mm": 1000.0 * float(residual[i]),
                        "match_free_space_mm": 1000.0 * float(np.sqrt(violation[i])),
                        "match_T_object_sensor": poses[i].tolist(),
                    },
                )
            )
        return out
