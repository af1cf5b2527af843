"""Where to touch next: a reachable contact whose expected patch differs most between the pose hypotheses.

When the two contacts leave several poses (the pose is `ambiguous`), one more touch can tell them apart. Each
candidate touch is a surface location of the object under the most probable hypothesis, pressed along its
inward normal by one sensor while the other stays. Under hypothesis k the same press in the world meets the
object's surface elsewhere, or not at all: its expected patch is the object's height over the pad under that
hypothesis, read off the surface distance field at points of the pad's disc. The candidate's value is the
expected disagreement between hypotheses, over the pad's points,

    mean_pad sqrt( sum over k, l of p_k p_l (h_k - h_l)^2 )     (heights clipped at `clip_m`),

and the chosen touch is the most valuable one that the sensor can make: approaching along its axis under any
hypothesis, its gel meets the object before its body does (housing and probe, as the contact simulator models a
GelSight Mini), and it clears the sensor that stays. The result is {p_object, n_object} in the mesh file's frame
(SPEC), plus the sensor to move and the world pose to press from.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import Any

import numpy as np

from yoto.contacts import SIDES, ContactPair
from yoto.geometry import (
    invert_transform,
    make_transform,
    rotate_vectors,
    rotation_between,
    tangent_basis,
    transform_points,
)
from yoto.objects.model import ObjectModel
from yoto.pose.field import SurfaceField, surface_field
from yoto.pose.hypotheses import Hypotheses
from yoto.pose.search import surface_samples
from yoto.sensor.spec import GELSIGHT_MINI
from yoto.simulate.body import SensorBody
from yoto.simulate.scenarios import boxes_overlap

Z_AXIS = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class NextTouchConfig:
    """How the next touch is chosen."""

    candidates: int = 1500  # surface locations considered (a deterministic stride through the search samples),
    # those a sensor can press kept (once per model)
    pad_radius_m: float = 0.006  # the expected patch is compared within this radius of the touch
    pad_rings: int = 2  # rings of comparison points on the pad disc (plus its centre)
    clip_m: float = 0.003  # heights further off than this count as this (no contact at all reads the same)
    min_probability: float = 0.0  # hypotheses below this are ignored for reachability (0: the sensor must clear the
    # object under every reported hypothesis: any of them may be the truth)
    press_depth_m: float = 0.0015  # the deepest press (the contact simulator's, and SPEC's, range ends here)
    clearance_m: float = 0.0002  # ... after which the sensor body must stay this far outside the object
    body_spacing_m: float = 0.003  # spacing of the points checked on the sensor body's boxes
    approach_travel_m: float = 0.05  # a sensor whose gel meets nothing within this travel misses the object
    approach_steps: int = 40  # steps of the approach's sphere tracing at most
    touch_tolerance_m: float = 5e-5  # the gel touches when its nearest point is this close to the surface
    contact_depth_m: float = 0.0005  # a press this shallow (SPEC's shallowest) ...
    min_contact_m2: float = 6e-6  # ... must make a contact this large where it must be informative (not a tip,
    # a corner or a rim, which a sensor cannot read as a patch)
    contact_spacing_m: float = 0.001  # spacing of the gel points that measure the contact
    min_crossing_width_m: float = 0.0035  # ... and a contact crossing the pad must be at least this wide at every
    # depth of the press (a thinner one is an edge or a ridge, a line the pad cannot read as a patch). Measured on
    # the object's penetration, which is ~1 mm wider than the gel's contact (the gel sinks in around a ridge)
    informative_probability: float = 0.05  # under hypotheses holding at least this, the press must make a contact
    checked: int = 300  # most valuable candidates checked for reachability under every hypothesis (best first)


@dataclass
class NextTouch:
    """A suggested touch: where (object frame, under the first hypothesis), which sensor, and its value."""

    p_object: np.ndarray  # (3,) canonical object frame
    n_object: np.ndarray  # (3,) outward normal there (press along -n)
    sensor: str  # "left" or "right": the sensor to move (the other stays)
    T_world_sensor: np.ndarray  # (4, 4) where the moving sensor should be when the gel meets the surface
    disagreement_m: float  # expected height difference between hypotheses at the touch (RMS over their pairs)

    def to_json(self, model: ObjectModel) -> dict[str, Any]:
        return {
            "p_object": transform_points(model.T_mesh_object, self.p_object).tolist(),
            "n_object": rotate_vectors(model.T_mesh_object, self.n_object).tolist(),
            "sensor": self.sensor,
            "T_world_sensor": self.T_world_sensor.tolist(),
            "expected_disagreement_mm": 1000.0 * self.disagreement_m,
        }


def _pad_points(config: NextTouchConfig) -> np.ndarray:
    """(P, 2) comparison points on the pad disc: its centre and `pad_rings` rings of six."""
    points = [np.zeros(2)]
    for ring in range(1, config.pad_rings + 1):
        radius = config.pad_radius_m * ring / config.pad_rings
        angles = np.arange(6) * np.pi / 3 + (ring % 2) * np.pi / 6
        points += list(radius * np.stack([np.cos(angles), np.sin(angles)], axis=1))
    return np.array(points)


def sensor_pose_at(p_object: np.ndarray, n_object: np.ndarray) -> np.ndarray:
    """T_object_sensor of a sensor whose gel centre touches `p_object`, pressing along -n (SPEC sensor frame)."""
    rotation = rotation_between(Z_AXIS, -np.asarray(n_object, dtype=np.float64))
    return make_transform(rotation, np.asarray(p_object, dtype=np.float64))


def _body_points(config: NextTouchConfig, body: SensorBody) -> np.ndarray:
    """Points on the surfaces of the sensor body's boxes (housing, probe), sensor frame."""
    points = []
    for centre, half in body.boxes(GELSIGHT_MINI, with_gel=False):
        axes = [np.linspace(-h, h, max(2, int(np.ceil(2 * h / config.body_spacing_m)) + 1)) for h in half]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        on_face = np.any(np.isclose(np.abs(grid), half, rtol=0, atol=1e-9), axis=1)
        points.append(grid[on_face] + centre)
    return np.vstack(points)


@dataclass
class TouchSites:
    """The surface locations a sensor can press on the object (pose-independent: the object alone in the way)."""

    p_object: np.ndarray  # (C, 3)
    n_object: np.ndarray  # (C, 3) outward normals (press along -n)
    T_object_sensor: np.ndarray  # (C, 4, 4) the sensor whose gel centre touches there


_SITES: dict[tuple[str, NextTouchConfig], TouchSites] = {}
_SITES_LOCK = threading.Lock()


def touch_sites(model: ObjectModel, config: NextTouchConfig = NextTouchConfig()) -> TouchSites:
    """The cached reachable sites of a model: a deterministic stride through the search samples, kept where a
    sensor pressing along the inward normal meets the object with its gel before its body does."""
    key = (model.fingerprint, config)
    with _SITES_LOCK:
        cached = _SITES.get(key)
    if cached is None:
        samples = surface_samples(model)
        stride = max(1, len(samples.points_object) // config.candidates)
        p, n = samples.points_object[::stride], samples.normals_object[::stride]
        T_object_sensor = np.stack([sensor_pose_at(point, normal) for point, normal in zip(p, n)])
        clear = presses_clear(surface_field(model), T_object_sensor, config, contact=True)
        cached = TouchSites(p[clear], n[clear], T_object_sensor[clear])
        with _SITES_LOCK:
            _SITES[key] = cached
    return cached


def suggest_next_touch(
    model: ObjectModel, hypotheses: Hypotheses, pair: ContactPair, config: NextTouchConfig = NextTouchConfig()
) -> NextTouch | None:
    """The most informative reachable touch (see the module docstring), or None when no candidate tells the
    hypotheses apart or none can be reached."""
    if len(hypotheses) < 2:
        return None
    field = surface_field(model)
    sites = touch_sites(model, config)
    p, n = sites.p_object, sites.n_object
    u, v = tangent_basis(n)
    pad = _pad_points(config)
    # World positions of the pad's comparison points for a press at each candidate, under the first hypothesis.
    pad_object = p[:, None, :] + pad[None, :, 0, None] * u[:, None, :] + pad[None, :, 1, None] * v[:, None, :]
    T0 = hypotheses.T_world_object[0]
    pad_world = transform_points(T0, pad_object)
    probability = hypotheses.probability / hypotheses.probability.sum()
    inverse = invert_transform(hypotheses.T_world_object)
    heights = []
    for T_object_world in inverse:
        local = transform_points(T_object_world, pad_world)
        distance, _ = field.distance(local, with_gradient=False)
        heights.append(np.clip(distance, -config.clip_m, config.clip_m))
    h = np.stack(heights)  # (H, C, P)
    # sum over k, l of p_k p_l (h_k - h_l)^2 = 2 Var_p(h): the spread of the expected patch between hypotheses.
    mean = np.einsum("k,kcp->cp", probability, h)
    variance = np.einsum("k,kcp->cp", probability, h**2) - mean**2
    disagreement = np.sqrt(2.0 * np.maximum(variance, 0.0)).mean(axis=1)
    order = np.argsort(-disagreement, kind="stable")[: config.checked]
    order = order[disagreement[order] > 1e-6]
    # The press planned under the first hypothesis must clear the object under every other one too, and make a
    # contact under each probable one (a press that misses, or touches a rim or a tip, tells nothing if that one is
    # the truth).
    T_world_new = T0 @ sites.T_object_sensor[order]
    clear = np.ones(len(order), dtype=bool)
    for T_object_world, share in zip(inverse[1:], probability[1:]):
        if share < config.min_probability:
            continue
        if not clear.any():
            break
        contact = bool(share >= config.informative_probability)
        clear[clear] = presses_clear(field, T_object_world @ T_world_new[clear], config, contact)
    T_world_sensor = {side: pair.contact(side).T_world_sensor for side in SIDES}
    boxes = SensorBody().boxes(GELSIGHT_MINI, with_gel=True)
    for index, T_new in zip(order[clear], T_world_new[clear]):
        for side, other in (("left", "right"), ("right", "left")):
            if not any(
                boxes_overlap(T_new, ca, ha, T_world_sensor[other], cb, hb) for ca, ha in boxes for cb, hb in boxes
            ):
                return NextTouch(p[index], n[index], side, T_new, float(disagreement[index]))
    return None


def _gel_points(spacing_m: float) -> np.ndarray:
    """Points on the undeformed gel surface (z = 0) over the pad, about `spacing_m` apart, sensor frame."""
    width, height = GELSIGHT_MINI.pad_size_m
    x, y = np.meshgrid(
        np.linspace(-width / 2, width / 2, int(width / spacing_m) + 1),
        np.linspace(-height / 2, height / 2, int(height / spacing_m) + 1),
    )
    return np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])


def presses_clear(
    field: SurfaceField, T_object_sensor: np.ndarray, config: NextTouchConfig, contact: bool = False
) -> np.ndarray:
    """(C,) whether sensors approaching along their z toward these poses (object frame, (C, 4, 4)) press the
    object with their gel before any part of their body meets it: each sensor moves along its z until its gel first
    touches (however far that is, `approach_travel_m` at most), presses `press_depth_m` further, and its body must
    then stay `clearance_m` outside the object. An approach that meets nothing cannot collide either; with
    `contact`, it must meet the object, and pressed `contact_depth_m` make a contact of `min_contact_m2`."""
    if not len(T_object_sensor):
        return np.zeros(0, dtype=bool)
    gel, body = _gel_points(config.body_spacing_m), _body_points(config, SensorBody())
    travel, touched, missed = _approach(field, T_object_sensor, gel, config)
    body_object = _advanced(T_object_sensor, travel + config.press_depth_m, body)
    body_distance, _ = field.distance(body_object, with_gradient=False)
    pressed = touched & (body_distance.min(axis=1) >= config.clearance_m)
    if not contact:
        return missed | pressed
    # Pressed the shallowest, halfway and the deepest: a contact of `min_contact_m2` at the shallowest, and no thin
    # strip across the pad at any of the three.
    gel = _gel_points(config.contact_spacing_m)
    informative = pressed.copy()
    for depth_m in (config.contact_depth_m, (config.contact_depth_m + config.press_depth_m) / 2, config.press_depth_m):
        depth, _ = field.distance(_advanced(T_object_sensor, travel + depth_m, gel), with_gradient=False)
        touching = depth < 0.0
        if depth_m == config.contact_depth_m:
            informative &= np.count_nonzero(touching, axis=1) * config.contact_spacing_m**2 >= config.min_contact_m2
        informative &= ~_thin_crossing(touching, gel, config)
    return informative


def _thin_crossing(touching: np.ndarray, gel: np.ndarray, config: NextTouchConfig) -> np.ndarray:
    """(C,) whether each contact (C, P) on the gel grid `gel` (P, 3, `_gel_points`) crosses the pad as a thin strip:
    it meets the pad's border in two or more separate runs and its mean width (its area over its length along its
    principal axis) is below `min_crossing_width_m`."""
    x, y = gel[:, 0], gel[:, 1]
    columns, rows = len(np.unique(x)), len(np.unique(y))
    grid = np.arange(len(gel)).reshape(rows, columns)
    ring = np.concatenate([grid[0, :-1], grid[:-1, -1], grid[-1, :0:-1], grid[:0:-1, 0]])  # circular order
    border = touching[:, ring]
    runs = np.count_nonzero(border & ~np.roll(border, 1, axis=1), axis=1)
    runs[border.all(axis=1)] = 1
    count = np.maximum(np.count_nonzero(touching, axis=1), 1)
    mean_x, mean_y = (touching @ x) / count, (touching @ y) / count
    dx, dy = x[None] - mean_x[:, None], y[None] - mean_y[:, None]
    sxx, syy, sxy = (np.sum(touching * d, axis=1) for d in (dx * dx, dy * dy, dx * dy))
    angle = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)  # the principal axis of each contact
    along = dx * np.cos(angle)[:, None] + dy * np.sin(angle)[:, None]
    length = np.maximum(
        np.where(touching, along, -np.inf).max(axis=1) - np.where(touching, along, np.inf).min(axis=1), 0
    )
    width = count * config.contact_spacing_m**2 / (length + config.contact_spacing_m)
    return (runs >= 2) & (width < config.min_crossing_width_m)


def _advanced(T_object_sensor: np.ndarray, travel: np.ndarray, points_sensor: np.ndarray) -> np.ndarray:
    """(C, P, 3) object-frame places of the sensor-frame points (P, 3) once each of the C sensors has moved `travel`
    (C,) along its z from its pose (C, 4, 4)."""
    origin = T_object_sensor[:, :3, 3] + travel[:, None] * T_object_sensor[:, :3, 2]
    return np.einsum("cij,pj->cpi", T_object_sensor[:, :3, :3], points_sensor) + origin[:, None, :]


def _approach(
    field: SurfaceField, T_object_sensor: np.ndarray, gel: np.ndarray, config: NextTouchConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far each sensor moves along its z (negative: back) until its gel first touches the object, whether it
    touched, and whether it met nothing within `approach_travel_m` (an approach that neither touched nor missed
    within `approach_steps` is neither, and counts as blocked). Sphere tracing: the gel's nearest distance to the
    surface is a step it can always take; the field is clamped at its band, so a sensor far off advances a band
    per step."""
    count = len(T_object_sensor)
    travel = np.zeros(count)
    moving = np.ones(count, dtype=bool)
    for _ in range(config.approach_steps):
        index = np.flatnonzero(moving)
        distance, _ = field.distance(_advanced(T_object_sensor[index], travel[index], gel), with_gradient=False)
        step = distance.min(axis=1)
        travel[index] += step
        moving[index] = (np.abs(step) > config.touch_tolerance_m) & (np.abs(travel[index]) < config.approach_travel_m)
        if not moving.any():
            break
    missed = np.abs(travel) >= config.approach_travel_m
    return travel, ~moving & ~missed, missed
