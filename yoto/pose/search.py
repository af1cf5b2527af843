"""The joint two-contact search: every pair of surface locations whose geometry fits the measured pair.

Two contacts measured in the world give a key that no rigid motion changes: their separation and the three
angles between the contact-to-contact direction d and the two outward normals (d, nL), (d, nR), (nL, nR)
(Drost et al.'s oriented point-pair feature, which the paper's solver is built on). A localizer returns the few
places each contact looks most like; on a flat face, a cylinder or a rounded edge a contact looks like every
place of that kind, and the true one is often not among them. The search covers them all:

1. Once per object model (`surface_samples`, cached): the surface sampled every ~2 mm, each sample with its
   outward normal and its local shape (the principal curvatures of a quadric fitted to what a gel pressed there
   would touch).
2. Per contact (`contact_locations`): the samples whose local shape matches the contact's own (curvatures
   within a tolerance that grows with how badly the quadric fits the contact: flat faces admit only flat
   samples, an edge only edges), plus the localizer's candidates.
3. Per pair (`search_poses`): every left x right location pair whose key fits the measured key within the
   tolerances (the sensors' calibration error, the localizers' error, and the blur of the sampling, which is
   larger where the normal turns quickly), solved in closed form (`solver.closed_form_quaternions`, vectorised). Large
   location sets are thinned on a coarser grid first (`thin`: one sample per voxel, evenly, whatever the curvature;
   the localizers' candidates are always kept), so a query costs at most `pair_budget` key evaluations. On rims
   and rounded edges a thinned location's normal can then lie 15-20 deg from the contact's, and the closed-form
   poses of the pairs near the truth are turned 7-14 deg off it (docs/journal/pose.md: where the missing truths are
   lost).

The pose stage verifies the matches with both tactile clouds.

Unlike Drost et al. there is no precomputed table of all sample pairs: it grows as the square of the samples
(a 2 mm sampling of a cereal box holds 10^8 pairs), and the coarse sampling that keeps it small cannot follow a
rounded edge, where the normal turns by tens of degrees between samples. The local-shape filter makes the
per-query pair sets small instead.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from yoto.contacts import SIDES, ContactEstimate, WorldContact
from yoto.geometry import normalize, tangent_basis
from yoto.objects.cache import ModelCache
from yoto.objects.model import ObjectModel
from yoto.pointcloud import voxel_downsample
from yoto.pose.kernels import SEARCH_KERNELS
from yoto.pose.solver import (
    MIN_CONTACT_SEPARATION_M,
    closed_form_quaternions,
    direction_angles,
    poses_from_quaternions,
    quaternion_rotation_vectors,
)


@dataclass(frozen=True)
class SampleConfig:
    """How the surface is sampled for the search (once per object model; the cache is keyed on it)."""

    spacing_m: float = 0.002  # sample spacing (grows for large objects, see max_samples)
    max_samples: int = 30_000  # samples at most
    normal_neighbours: int = 20  # k of each sample's aggregated normal (as the localizers report them)
    shape_radius_m: float = 0.004  # local shape (principal curvatures) fitted within this radius of a location ...
    shape_depth_m: float = 0.002  # ... to the surface at most this far below its tangent plane: what a gel pressed
    # there can touch (not the other side of an edge or of a thin wall)


@dataclass(frozen=True)
class SearchConfig:
    """How a measured pair is looked up (per query)."""

    samples: SampleConfig = SampleConfig()
    distance_tolerance_m: float = 0.003  # key tolerance besides the sampling's own blur: separation ...
    angle_tolerance_rad: float = float(np.radians(8.0))  # ... and angles (calibration error, normal noise)
    candidate_angle_tolerance_rad: float = float(np.radians(20.0))  # angles of a localizer's candidate (its normal
    # is read at a point, the sensor's over a 2 mm disc: on edges and ridges they differ)
    curvature_floor: float = 12.0  # 1/m: a sample matches a contact's shape when both curvatures agree within
    # (floor + the contact's larger |curvature|) x (share + residual / residual_scale): a quadric fits a flat face
    # or a cylinder well and its curvatures are then sharp; on an edge or a bump they are only a rough guide
    curvature_share: float = 0.35
    curvature_residual_scale_m: float = 0.00015
    pair_budget: int = 4_000_000  # location pairs evaluated at most per query (large sets are thinned)
    max_matches: int = 8000  # matches kept (the best keys first)


@dataclass
class LocalShape:
    """The shape of a surface around locations: principal curvatures of a quadric fitted there, and its fit."""

    curvatures: np.ndarray  # (K, 2) 1/m, larger first; positive where the surface curves away from its normal
    rms_m: np.ndarray  # (K,) RMS residual of the quadric fit: small on featureless (flat, cylindrical...) surface


def fit_local_shapes(
    points: np.ndarray, centres: np.ndarray, normals: np.ndarray, neighbours: np.ndarray, valid: np.ndarray
) -> LocalShape:
    """Quadric fits h = (a x^2 + 2 b xy + c y^2) / 2 + d x + e y + f in each centre's tangent frame.

    `neighbours` (K, N) indexes `points` for each of K centres (with outward `normals`); `valid` (K, N) says
    which entries count. Fewer than 10 valid points give an infinite residual.
    """
    u, v = tangent_basis(normals)
    offset = points[neighbours] - centres[:, None, :]
    x, y = np.einsum("knj,kj->kn", offset, u), np.einsum("knj,kj->kn", offset, v)
    h = np.einsum("knj,kj->kn", offset, normals)
    design = np.stack([x * x / 2, x * y, y * y / 2, x, y, np.ones_like(x)], axis=-1) * valid[..., None]
    gram = np.einsum("kni,knj->kij", design, design) + 1e-15 * np.eye(6)
    coefficients = np.linalg.solve(gram, np.einsum("kni,kn->ki", design, h * valid)[..., None])[..., 0]
    residual = np.sum((np.einsum("kni,ki->kn", design, coefficients) - h * valid) ** 2, axis=1)
    count = valid.sum(axis=1)
    hessian = -np.stack(
        [
            np.stack([coefficients[:, 0], coefficients[:, 1]], -1),
            np.stack([coefficients[:, 1], coefficients[:, 2]], -1),
        ],
        axis=-2,
    )
    curvatures = np.linalg.eigvalsh(hessian)[:, ::-1]
    rms = np.sqrt(residual / np.maximum(count, 1))
    return LocalShape(curvatures, np.where(count >= 10, rms, np.inf))


def contact_shape(points_sensor: np.ndarray, p_sensor: np.ndarray, n_sensor: np.ndarray, config: SampleConfig):
    """The local shape (one row) of a tactile contact around its measured centre and outward normal."""
    points_sensor = points_sensor[:: max(1, len(points_sensor) // 4000)]
    offset = points_sensor - p_sensor
    along = offset @ n_sensor
    keep = np.flatnonzero(np.sum(offset**2, axis=1) - along**2 <= config.shape_radius_m**2)
    if len(keep) > 2000:
        keep = keep[np.linspace(0, len(keep) - 1, 2000).astype(np.int64)]
    valid = np.ones((1, len(keep)), dtype=bool)
    return fit_local_shapes(points_sensor, p_sensor[None], n_sensor[None], keep[None], valid)


@dataclass
class SurfaceSamples:
    """The object's surface sampled for the search: locations, outward normals, local shapes (object frame)."""

    points_object: np.ndarray  # (M, 3)
    normals_object: np.ndarray  # (M, 3)
    shapes: LocalShape  # (M,)
    spacing_m: float
    seconds: float  # time to build
    curvature_columns: np.ndarray = field(init=False)  # (2, M) the curvatures as contiguous rows (for the queries)
    largest_curvature: np.ndarray = field(init=False)  # (M,) the larger |curvature| of each sample

    def __post_init__(self) -> None:
        self.curvature_columns = np.ascontiguousarray(self.shapes.curvatures.T)
        self.largest_curvature = np.abs(self.shapes.curvatures).max(axis=1)


def build_surface_samples(model: ObjectModel, config: SampleConfig = SampleConfig()) -> SurfaceSamples:
    """Sample the model's surface and fit each sample's local shape (see SampleConfig)."""
    start = time.perf_counter()
    spacing = max(config.spacing_m, float(np.sqrt(model.meta["surface_area_m2"] / config.max_samples)))
    points = model.points_object.astype(np.float64)
    while True:
        (centres,) = voxel_downsample(points, spacing)
        if len(centres) <= config.max_samples:
            break
        spacing *= 1.05
    samples = model.nearest_surface_point(centres)
    normals = model.aggregated_normal(samples, config.normal_neighbours)
    k = int(min(len(points), np.ceil(2.5 * np.pi * (config.shape_radius_m / model.point_spacing_m) ** 2)))
    parts = []
    for first in range(0, len(samples), 256):
        centre, axis = samples[first : first + 256], normals[first : first + 256]
        _, neighbours = model.kdtree.query(centre, k=k)
        offset = model.points_object[neighbours] - centre[:, None, :]
        height = np.einsum("knj,kj->kn", offset, axis)
        lateral = np.sum(offset**2, axis=-1) - height**2
        facing = np.einsum("knj,kj->kn", model.normals_object[neighbours], axis) > 0.7
        valid = facing & (height > -config.shape_depth_m) & (lateral <= config.shape_radius_m**2)
        parts.append(fit_local_shapes(model.points_object, centre, axis, neighbours, valid))
    shapes = LocalShape(np.concatenate([p.curvatures for p in parts]), np.concatenate([p.rms_m for p in parts]))
    return SurfaceSamples(samples, normals, shapes, spacing, time.perf_counter() - start)


_CACHE: ModelCache[SampleConfig, SurfaceSamples] = ModelCache(build_surface_samples, size=4)


def surface_samples(model: ObjectModel, config: SampleConfig = SampleConfig()) -> SurfaceSamples:
    """The cached search samples of a model (built on first use)."""
    return _CACHE.get(model, config)


@dataclass
class Locations:
    """Where one contact may be: oriented surface locations (object frame), with how blurred each is."""

    p_object: np.ndarray  # (L, 3)
    n_object: np.ndarray  # (L, 3)
    blur_m: np.ndarray  # (L,) how far the contact may lie from the location (0 for a candidate; for a sample, the
    # distance to the next sample: spacing / sqrt(2))
    curvature: np.ndarray  # (L,) 1/m, the larger principal curvature's magnitude (0 for a candidate)
    candidate: np.ndarray  # (L,) bool: a localizer's candidate (else a surface sample)

    def normal_blur_rad(self, config: SearchConfig) -> np.ndarray:
        """How far the contact's normal may turn from the location's: the curvature times the blur for a sample."""
        return np.where(
            self.candidate, config.candidate_angle_tolerance_rad, np.minimum(self.curvature * self.blur_m, np.pi)
        )

    def subset(self, index: np.ndarray) -> Locations:
        return Locations(*(getattr(self, name)[index] for name in self.__dataclass_fields__))


def contact_locations(
    samples: SurfaceSamples,
    shape: LocalShape,
    candidates: list[ContactEstimate],
    config: SearchConfig,
    with_samples: bool = True,
) -> Locations:
    """The localizer's candidates and (`with_samples`) every surface sample whose local shape matches the contact's."""
    fits = np.empty(0, dtype=np.int64)
    if with_samples:
        tolerance = (config.curvature_floor + np.abs(shape.curvatures[0]).max()) * (
            config.curvature_share + min(float(shape.rms_m[0]), 1e-3) / config.curvature_residual_scale_m
        )
        larger, smaller = samples.curvature_columns
        fits = np.flatnonzero(
            (np.abs(larger - shape.curvatures[0, 0]) <= tolerance)
            & (np.abs(smaller - shape.curvatures[0, 1]) <= tolerance)
        )
    count = len(candidates)
    return Locations(
        np.vstack([np.array([c.p_object for c in candidates]).reshape(-1, 3), samples.points_object[fits]]),
        np.vstack([np.array([c.n_object for c in candidates]).reshape(-1, 3), samples.normals_object[fits]]),
        np.concatenate([np.zeros(count), np.full(len(fits), samples.spacing_m / np.sqrt(2.0))]),
        np.concatenate([np.zeros(count), samples.largest_curvature[fits]]),
        np.concatenate([np.ones(count, dtype=bool), np.zeros(len(fits), dtype=bool)]),
    )


def thin(locations: Locations, spacing_m: float) -> Locations:
    """Keep one sample per voxel of `spacing_m` (the first, and every candidate): a coarser sampling, blurred
    accordingly."""
    samples = np.flatnonzero(~locations.candidate)
    cells = np.floor(locations.p_object[samples] / spacing_m).astype(np.int64)
    cells -= cells.min(axis=0, initial=0)
    span = cells.max(axis=0, initial=0) + 1
    key = (cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    if np.prod(span) <= 1 << 20:
        # The first sample of each voxel without sorting: written in reverse order, the first one's index stays.
        first = np.empty(int(np.prod(span)), dtype=np.int64)
        order = np.arange(len(key))
        first[key[::-1]] = order[::-1]
        kept = samples[first[key] == order]
    else:  # a grid too large to hold
        kept = samples[np.sort(np.unique(key, return_index=True)[1])]
    thinned = locations.subset(np.concatenate([np.flatnonzero(locations.candidate), kept]))
    thinned.blur_m = np.where(thinned.candidate, 0.0, np.maximum(thinned.blur_m, spacing_m / np.sqrt(2.0)))
    return thinned


@dataclass
class PairMatches:
    """Pairs of locations that fit a measured pair, and the closed-form pose of each (arrays over K)."""

    mismatch: np.ndarray  # (K,) key mismatch in tolerances (0: exact; at most 1)
    quaternions_xyzw: np.ndarray  # (K, 4) the closed-form pose of each: its rotation (w >= 0) ...
    translations: np.ndarray  # (K, 3) ... and translation (T_world_object)

    def __len__(self) -> int:
        return len(self.mismatch)

    @property
    def T_world_object(self) -> np.ndarray:
        """(K, 4, 4) the closed-form poses."""
        return poses_from_quaternions(self.quaternions_xyzw, self.translations)

    @property
    def rotation_vectors(self) -> np.ndarray:
        """(K, 3) the poses' rotations as rotation vectors (angles in [0, pi])."""
        return quaternion_rotation_vectors(self.quaternions_xyzw)

    def subset(self, index: np.ndarray) -> PairMatches:
        return PairMatches(self.mismatch[index], self.quaternions_xyzw[index], self.translations[index])


Matched = tuple[np.ndarray, np.ndarray, np.ndarray]  # left and right location indices of the pairs that fit, and
# each pair's key mismatch (in tolerances)


@dataclass
class KeyTest:
    """What the search tests every left x right location pair with: the measured key, and each location's terms of
    it (rows: left locations, columns: right locations; object frame)."""

    separation: float  # measured |pR - pL| (m)
    angles: np.ndarray  # (3,) measured angles (d, nL), (d, nR), (nL, nR)
    distance_tolerance_m: float  # separation tolerance besides the locations' blur
    angle_variance: float  # squared angle tolerance besides the locations' normal blur
    left_rows: np.ndarray  # (L, 4) [pL, 1]
    right_columns: np.ndarray  # (4, R) [-2 pR, |pR|^2]
    low_rows: np.ndarray  # (L,) the widest shell's squared inner bound less |pL|^2 ...
    high_rows: np.ndarray  # (L,) ... and its outer bound
    squared_left: np.ndarray  # (L,) |pL|^2
    own_left: np.ndarray  # (L,) pL . nL
    own_right: np.ndarray  # (R,) pR . nR
    p_left_columns: np.ndarray  # (3, L) coordinates as contiguous rows (`_dot`)
    p_right_columns: np.ndarray  # (3, R)
    n_left_columns: np.ndarray  # (3, L)
    n_right_columns: np.ndarray  # (3, R)
    left_blur_m: np.ndarray  # (L,) Locations.blur_m
    right_blur_m: np.ndarray  # (R,)
    left_variance: np.ndarray  # (L,) angle variance plus the left location's normal blur squared
    right_turn2: np.ndarray  # (R,) the right location's normal blur squared

    @property
    def rows(self) -> int:
        return len(self.left_rows)

    @property
    def chunk(self) -> int:
        """Left locations tested per matrix product (~400k pairs); a split of the rows falls between chunks."""
        return max(1, 400_000 // max(self.right_columns.shape[1], 1))


def key_matches(test: KeyTest, first: int = 0, stop: int | None = None) -> Matched:
    """The pairs of left locations `first` to `stop` (`first` a multiple of `test.chunk`) with every right location
    whose key fits, in row order: rows tested in two parts and joined give the same arrays as all at once.

    The shell of the widest separation tolerance over all left x right pairs, by one matrix product per chunk:
    [pL, 1] . [-2 pR, |pR|^2] = |pR - pL|^2 - |pL|^2, compared with the shell's bounds less |pL|^2 (one pass fewer
    over the chunk than forming the squared distances). On what falls in the shell, each part of the key is tested
    in turn on the pairs the parts before it kept, the most selective first: the angle (nL, nR), then the separation
    with its own tolerance, then the angles (d, nL), (d, nR) from dot products (offset . n = pR . n - pL . n, each
    location's own term computed once). Compiled (`kernels.key_candidates`, numba), the shell and every test run
    pair by pair without an arccos, keeping a superset (within 1e-6 of the tolerances), and the numpy tests
    above decide on what it keeps: the same pairs, order and mismatches bitwise (numba's arccos is libm's, which
    differs from numpy's in the last place).
    """
    t = test
    stop = t.rows if stop is None else stop
    columns, chunk = t.right_columns.shape[1], t.chunk
    found = []
    # Work buffers reused by every chunk (fresh multi-megabyte arrays cost page faults each time).
    partial_buffer = np.empty((min(chunk, max(stop - first, 0)), columns))
    if SEARCH_KERNELS is None:
        low_buffer = np.empty(partial_buffer.shape, dtype=bool)
        high_buffer = np.empty_like(low_buffer)
    else:
        kept_buffer = np.empty(partial_buffer.size, dtype=np.int64)
    for start in range(first, stop, chunk):
        rows = slice(start, min(start + chunk, stop))
        count = rows.stop - start
        partial = np.matmul(t.left_rows[rows], t.right_columns, out=partial_buffer[:count])
        if SEARCH_KERNELS is None:
            shell = np.greater_equal(partial, t.low_rows[rows, None], out=low_buffer[:count])
            shell &= np.less_equal(partial, t.high_rows[rows, None], out=high_buffer[:count])
            flat = np.flatnonzero(shell)  # far faster than a 2-D nonzero; the same pairs in the same order
        else:  # the shell's pairs that fit within a hair over the tolerances: the tests below decide, as above
            flat = kept_buffer[: _compiled_key_candidates(t, partial, start, kept_buffer)]
        if not len(flat):
            continue
        i = flat // columns
        j = flat - i * columns
        i += start
        # (nL, nR)
        key = np.arccos(np.clip(_dot(t.n_left_columns, i, t.n_right_columns, j), -1.0, 1.0))
        mismatch = np.abs(key - t.angles[2]) / np.sqrt(t.left_variance[i] + t.right_turn2[j])
        keep = np.flatnonzero(mismatch <= 1.0)
        i, j, flat, mismatch = i[keep], j[keep], flat[keep], mismatch[keep]
        # separation
        distance = np.sqrt(np.maximum(partial.reshape(-1)[flat] + t.squared_left[i], 0.0))
        blur = t.left_blur_m[i] + t.right_blur_m[j]
        part = np.abs(distance - t.separation) / np.hypot(t.distance_tolerance_m, blur)
        keep = np.flatnonzero((part <= 1.0) & (distance >= MIN_CONTACT_SEPARATION_M))
        i, j, distance, blur = i[keep], j[keep], distance[keep], blur[keep]
        mismatch = np.maximum(mismatch[keep], part[keep])
        turn2 = (blur / max(t.separation, 1e-3)) ** 2  # the direction d turns as the locations move within their blur
        # (d, nL) and (d, nR), d = (pR - pL) / distance
        length = np.maximum(distance, 1e-12)
        cosine = (_dot(t.p_right_columns, j, t.n_left_columns, i) - t.own_left[i]) / length
        key = np.arccos(np.clip(cosine, -1.0, 1.0))
        part = np.abs(key - t.angles[0]) / np.sqrt(t.left_variance[i] + turn2)
        cosine = (t.own_right[j] - _dot(t.p_left_columns, i, t.n_right_columns, j)) / length
        key = np.arccos(np.clip(cosine, -1.0, 1.0))
        part = np.maximum(part, np.abs(key - t.angles[1]) / np.sqrt(t.angle_variance + t.right_turn2[j] + turn2))
        keep = part <= 1.0
        found.append((i[keep], j[keep], np.maximum(mismatch[keep], part[keep])))
    if not found:
        return np.empty(0, np.int64), np.empty(0, np.int64), np.empty(0)
    a, b, mismatch = (np.concatenate(parts) for parts in zip(*found))
    return a, b, mismatch


def key_test(left: Locations, right: Locations, world: dict[str, WorldContact], config: SearchConfig) -> KeyTest:
    """The key test of every `left` x `right` location pair against the measured pair `world` (see KeyTest)."""
    left_turn, right_turn = left.normal_blur_rad(config), right.normal_blur_rad(config)
    offset = world["right"].p_world - world["left"].p_world
    separation = float(np.linalg.norm(offset))
    angles = direction_angles(offset, world["left"].n_world, world["right"].n_world)
    n_left, n_right = normalize(left.n_object), normalize(right.n_object)
    widest = float(np.hypot(config.distance_tolerance_m, left.blur_m.max(initial=0) + right.blur_m.max(initial=0)))
    squared_left = np.sum(left.p_object**2, axis=1)
    angle_variance = config.angle_tolerance_rad**2
    return KeyTest(
        separation=separation,
        angles=angles,
        distance_tolerance_m=config.distance_tolerance_m,
        angle_variance=angle_variance,
        left_rows=np.column_stack([left.p_object, np.ones(len(left.p_object))]),
        right_columns=np.vstack([-2.0 * right.p_object.T, np.sum(right.p_object**2, axis=1)]),
        low_rows=max(separation - widest, 0.0) ** 2 - squared_left,
        high_rows=(separation + widest) ** 2 - squared_left,
        squared_left=squared_left,
        own_left=np.sum(left.p_object * n_left, axis=1),
        own_right=np.sum(right.p_object * n_right, axis=1),
        p_left_columns=np.ascontiguousarray(left.p_object.T),
        p_right_columns=np.ascontiguousarray(right.p_object.T),
        n_left_columns=np.ascontiguousarray(n_left.T),
        n_right_columns=np.ascontiguousarray(n_right.T),
        left_blur_m=left.blur_m,
        right_blur_m=right.blur_m,
        left_variance=angle_variance + left_turn**2,
        right_turn2=right_turn**2,
    )


def search_poses(
    model: ObjectModel,
    world: dict[str, WorldContact],
    shapes: dict[str, LocalShape],
    candidates: dict[str, list[ContactEstimate]],
    config: SearchConfig = SearchConfig(),
    samples: bool = True,
    matcher: Callable[[KeyTest], Matched] | None = None,
    solver: Callable[..., tuple[np.ndarray, np.ndarray]] | None = None,
) -> PairMatches:
    """Every pair of locations (localizers' candidates and, with `samples`, matching surface samples) whose key fits
    the measured pair, with its closed-form pose; at most `max_matches`, the best fitting keys first. `matcher`
    tests the location pairs (`key_matches` on all rows; `executor.SplitExecutor.key_matches` on two cores),
    `solver` poses the matches (`solver.closed_form_quaternions`; `executor.SplitExecutor.closed_form` on two
    cores: row by row, the same numbers)."""
    surface = surface_samples(model, config.samples)
    left, right = (contact_locations(surface, shapes[side], candidates[side], config, samples) for side in SIDES)
    spacing = surface.spacing_m
    while len(left.p_object) * len(right.p_object) > config.pair_budget:
        spacing *= 1.5
        if len(left.p_object) >= len(right.p_object):
            left = thin(left, spacing)
        else:
            right = thin(right, spacing)
    test = key_test(left, right, world, config)
    a, b, mismatch = (key_matches if matcher is None else matcher)(test)
    if len(mismatch) > config.max_matches:
        best = np.argpartition(mismatch, config.max_matches - 1)[: config.max_matches]
        a, b, mismatch = a[best], b[best], mismatch[best]
    quaternions, translations = (closed_form_quaternions if solver is None else solver)(
        left.p_object[a],
        test.n_left_columns[:, a].T,
        right.p_object[b],
        test.n_right_columns[:, b].T,
        world["left"],
        world["right"],
    )
    return PairMatches(mismatch, quaternions, translations)


def _compiled_key_candidates(test: KeyTest, partial: np.ndarray, start: int, found: np.ndarray) -> int:
    """`kernels.key_candidates` on one chunk of `partial` (left locations from `start`): how many it wrote."""
    t = test
    return int(
        SEARCH_KERNELS.key_candidates(  # type: ignore[union-attr]
            partial,
            t.low_rows,
            t.high_rows,
            t.squared_left,
            t.p_left_columns,
            t.p_right_columns,
            t.n_left_columns,
            t.n_right_columns,
            t.own_left,
            t.own_right,
            t.left_variance,
            t.right_turn2,
            t.left_blur_m,
            t.right_blur_m,
            t.angles,
            t.separation,
            t.distance_tolerance_m,
            t.angle_variance,
            MIN_CONTACT_SEPARATION_M,
            start,
            found,
        )
    )


def _dot(first: np.ndarray, i: np.ndarray, second: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Dot products of the vectors i of `first` and j of `second` ((3, L) columns): the sum of the coordinates'
    products in order, as `np.sum(a * b, axis=1)` adds them, without gathering (N, 3) rows and summing along their
    short axis."""
    return first[0][i] * second[0][j] + first[1][i] * second[1][j] + first[2][i] * second[2][j]
