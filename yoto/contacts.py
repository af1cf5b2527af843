"""Tactile contacts: what a sensor measured, where a localizer put it, and the contact-pair file (SPEC: "Dual contact").

- `TactileContact` / `ContactPair`: tactile clouds (sensor frame) with the sensors' calibrated poses.
- `contact_in_sensor` / `WorldContact`: a contact's centre and outward normal as the sensor measured it.
- `ContactEstimate`: a contact located on the object model (object frame), the output of every localizer.

A pair file is JSON with fixed keys; its point clouds are PLY files next to it:
    {"object": NAME,
     "left":  {"points": "pair_0000_left.ply",  "T_world_sensor": 4x4},
     "right": {"points": "pair_0000_right.ply", "T_world_sensor": 4x4},
     "ground_truth": {"T_world_object": 4x4, "left_p_object": [x,y,z], "right_p_object": [x,y,z]}}
`ground_truth` is optional and is expressed in the mesh file's frame; in code that frame is called
`mesh` (`T_world_mesh`, `p_mesh`) to keep it apart from YOTO's canonical `object` frame.

A side may give a GelSight image instead of (or beside) its points (SPEC, "Dual contact"):
    "left": {"image": "pair_0000_left.png", "background": "left_background.png", "calibration": "mini.npz",
             "T_world_sensor": 4x4}
(paths relative to the JSON file; `background` and `calibration` optional). This module reads the keys; the
reconstruction is the sensor stage's (`yoto.sensor.pair_images.ImageSides`), passed to `read_contact_pair`.
"""

from __future__ import annotations

import os
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from yoto.errors import InputError, NoContactError
from yoto.geometry import normalize, rotate_vectors, transform_points, validate_transform
from yoto.io import read_json, read_ply_points, write_json_atomic, write_ply_points
from yoto.jit import ENABLED, jit
from yoto.pointcloud import covariance_eigh

SIDES = ("left", "right")
MIN_TACTILE_POINTS = 30  # fewer contact points than this cannot define a local surface
WELL_CONDITIONED = 0.15  # sigma_2 / sigma_1 of [d, n_L, n_R] below this: rotation about one axis is weakly fixed
LOCAL_FIT_RADIUS_M = 0.002  # radius of the surface patch fitted at the contact centre of a tactile cloud
LOCAL_FIT_MIN_POINTS = 12
LINE_POINTS = 8  # points averaged where the centroid's normal line meets the cloud
RECENT_CLOUDS = 4  # contact_in_sensor keeps its answers for this many clouds
# What the gel felt (`read_gel`, one rule for "is it pressed" and "which points are the untouched gel"):
# - the noise: 1 sigma of the heights, read off the points above the gel plane (z > 0 can only be noise) as the median
#   of that half-normal half (HALF_NORMAL_MEDIAN), so a few spikes do not count;
# - the noise floor: NOISE_MARGIN sigma, and at least NO_INDENTATION_M; the cloud is pressed when its deepest points
#   (the INDENTATION_POINTS-th deepest) lie deeper than it;
# - a whole pad (the untouched gel around the contact in the cloud, not contact points alone): at least
#   INDENTATION_POINTS and UNTOUCHED_SHARE of its points on or above the gel plane (the untouched gel's upper half:
#   4-80% in whole-pad clouds of 0.5-2 mm presses; a cloud of contact points alone with a noisy rim, 0.1-0.4% at
#   20 um noise), or at least INDENTATION_POINTS there and a cloud that spans the pad (`spans_the_pad`: a whole
#   pad whose gel a reconstruction's offset put below z = 0); docs/journal/formats.md, stop 15;
# - a whole pad's contact: its points deeper than the noise floor and than SINK_IN_SHARE of the depth (the gel sinks
#   in around a contact without touching the object; 0.05, the reconstruction's `felt_relative_depth`, left most of
#   a soft gel's ring; 0.1 took whole-pad poses from 30 to 34 of 40, the contact-only clouds' 35).
NO_INDENTATION_M = 5e-5
NOISE_MARGIN = 5.0
INDENTATION_POINTS = 20
UNTOUCHED_SHARE = 0.01
SINK_IN_SHARE = 0.1
# A tactile frame during motion whose deepest points lie less deep than this shows the object leaving the gel (a kiss
# over a few pixels, or no press at all): the closed loop does not register it (`GelReading.kiss`;
# docs/journal/formats.md, stop 16). YOTO's own frames lie at least 0.51 mm deep (12 825 frames of the tracking
# benchmark's seed 11).
KISS_DEPTH_M = 1e-4
MINI_PAD_M = (320 * 0.0634e-3, 240 * 0.0634e-3)  # SPEC's pad (yoto.sensor.spec's; this core module does not import it)
HALF_NORMAL_MEDIAN = 0.6745  # the median of |x| for x ~ N(0, 1): noise sigma from the median of its positive half


@dataclass(frozen=True)
class TactileImage:
    """A side given as a GelSight image (SPEC "Dual contact"); paths as found (absolute or relative to the cwd)."""

    image: Path  # the frame
    background: Path | None = None  # a no-contact frame of the same sensor and session (else the calibration's)
    calibration: Path | None = None  # the sensor's calibration file (else the reader's default)


# Turns an image side into its tactile cloud (N, 3), sensor frame, metres, and the 1-sigma of the log of its depth
# scale (TactileContact.depth_scale_sigma) (yoto.sensor.pair_images.ImageSides).
ImageReconstructor = Callable[[TactileImage], tuple[np.ndarray, float]]


@dataclass
class TactileContact:
    """One sensor's observation: its contact surface points (sensor frame) and where the sensor was."""

    points_sensor: np.ndarray  # (N, 3) metres, contact-surface points, z <= 0 where pressed
    T_world_sensor: np.ndarray  # (4, 4) the sensor's calibrated pose
    source: Path | None = None  # the PLY (or image) file it came from, for messages
    image: TactileImage | None = None  # the GelSight image the side gives, if any (kept on rewrite)
    depth_scale_sigma: float = 0.0  # 1-sigma of the log of the factor its heights may be off by (a cloud
    # reconstructed from an image: the reconstruction's; the pose stage then estimates the factor); 0: exact


@dataclass
class ContactPair:
    """A simultaneous dual contact, with its ground truth when known (mesh-file frame)."""

    object_name: str
    left: TactileContact
    right: TactileContact
    T_world_mesh_true: np.ndarray | None = None
    p_mesh_true: dict[str, np.ndarray] = field(default_factory=dict)  # side -> (3,) true contact location
    path: Path | None = None
    extra: dict[str, Any] = field(default_factory=dict)  # keys beyond SPEC's, kept on rewrite

    def contact(self, side: str) -> TactileContact:
        return self.left if side == "left" else self.right

    @property
    def has_ground_truth(self) -> bool:
        return self.T_world_mesh_true is not None and all(side in self.p_mesh_true for side in SIDES)


@dataclass
class ContactEstimate:
    """One contact located on the object model (object frame), with what the localizer knows of it."""

    p_object: np.ndarray  # (3,) contact location
    n_object: np.ndarray  # (3,) outward unit normal there (kNN-aggregated from the parent cloud)
    block: int = -1  # block index, -1 if the localizer has no blocks
    score: float = 0.0  # the localizer's own ranking score (higher is better); comparable within a method
    probability: float = 1.0  # the localizer's belief in this candidate, in [0, 1]
    details: dict = field(default_factory=dict)  # method-specific extras for result files


@dataclass
class WorldContact:
    """One contact as the sensor measured it: location and outward object normal, sensor and world frames."""

    p_sensor: np.ndarray
    n_sensor: np.ndarray
    p_world: np.ndarray
    n_world: np.ndarray


# contact_in_sensor's kept answers: (a copy of the cloud, (centre, normal)), oldest first.
_recent: deque[tuple[np.ndarray, tuple[np.ndarray, np.ndarray]]] = deque(maxlen=RECENT_CLOUDS)
_recent_lock = threading.Lock()


def contact_in_sensor(points_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Contact centre and outward object normal of a tactile cloud, in the sensor frame.

    The normal is that of a plane fitted to the points around the centroid, signed to point out of the
    object, i.e. toward the sensor (-z). The centre is where the line through the centroid along that
    normal meets the cloud (the surface point nearest the centroid, which is how ground-truth contact
    locations are defined); it is read off the few points closest to the line, so curvature adds no bias.

    The answers for the last `RECENT_CLOUDS` clouds are kept: a localizer and the pose stage both ask for the same
    cloud's (about a millisecond each), and a cloud equal to a kept one (same values, shape and dtype) is
    answered from it.
    """
    points_sensor = np.asarray(points_sensor)
    with _recent_lock:
        for cloud, (centre, normal) in _recent:
            if cloud.shape == points_sensor.shape and cloud.dtype == points_sensor.dtype:
                if np.array_equal(cloud, points_sensor):
                    return centre.copy(), normal.copy()
    centre, normal = _contact_in_sensor(points_sensor)
    with _recent_lock:
        _recent.append((np.array(points_sensor), (centre.copy(), normal.copy())))
    return centre, normal


def _contact_in_sensor(points_sensor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`contact_in_sensor`, computed."""
    # Column by column: numpy's mean over axis 0 of an (N, 3) array is ten times slower.
    centroid = np.array([points_sensor[:, axis].mean() for axis in range(3)])
    # Plain distances beat building a KD-tree for one query on a dense (~20k-point) tactile cloud.
    if ENABLED:
        dtype = np.result_type(points_sensor, centroid)  # float32 for a float32 cloud, as numpy's path
        offsets, from_centroid = np.empty((len(points_sensor), 3), dtype), np.empty(len(points_sensor), dtype)
        closest = _centroid_offsets(points_sensor, centroid, offsets, from_centroid)
    else:
        offsets = points_sensor - centroid
        from_centroid = np.einsum("ij,ij->i", offsets, offsets)
        closest = np.argmin(from_centroid)
    nearest = points_sensor[closest]
    # The patch lies within the fit radius of the point nearest the centroid, so within that point's distance from
    # the centroid plus the radius (squared, with a margin for rounding): only those points are measured.
    reach = (np.sqrt(from_centroid[closest]) + LOCAL_FIT_RADIUS_M) ** 2 * (1.0 + 1e-9) + 1e-18
    near = np.flatnonzero(from_centroid <= reach)
    from_nearest = points_sensor[near] - nearest
    squared = np.einsum("ij,ij->i", from_nearest, from_nearest)
    neighbours = near[squared <= LOCAL_FIT_RADIUS_M**2]
    if len(neighbours) < LOCAL_FIT_MIN_POINTS:
        from_nearest = points_sensor - nearest
        neighbours = np.argsort(np.einsum("ij,ij->i", from_nearest, from_nearest))[:LOCAL_FIT_MIN_POINTS]
    _, _, eigenvectors = covariance_eigh(points_sensor[neighbours])
    normal = eigenvectors[:, 0] if eigenvectors[2, 0] <= 0 else -eigenvectors[:, 0]
    along = offsets @ normal
    off_line = from_centroid - along * along  # squared distances from the line (Pythagoras; same order, no root)
    closest_to_line = np.argpartition(off_line, min(LINE_POINTS, len(off_line) - 1))[:LINE_POINTS]
    return centroid + along[closest_to_line].mean() * normal, normal


@jit
def _centroid_offsets(points, centroid, offsets, squared):
    """offsets = points - centroid and their squared norms (summed in `np.einsum`'s order: the same numbers); returns
    the index of the first smallest, as `np.argmin`."""
    closest = 0
    for n in range(points.shape[0]):
        x, y, z = points[n, 0] - centroid[0], points[n, 1] - centroid[1], points[n, 2] - centroid[2]
        offsets[n, 0], offsets[n, 1], offsets[n, 2] = x, y, z
        squared[n] = x * x + y * y + z * z
        if squared[n] < squared[closest]:
            closest = n
    return closest


def contact_in_world(contact: TactileContact) -> WorldContact:
    """The measured contact centre and outward normal of a tactile contact, in its sensor's and the world frame."""
    p_sensor, n_sensor = contact_in_sensor(contact.points_sensor)
    return WorldContact(
        p_sensor=p_sensor,
        n_sensor=n_sensor,
        p_world=transform_points(contact.T_world_sensor, p_sensor),
        n_world=rotate_vectors(contact.T_world_sensor, n_sensor),
    )


def dual_contact_directions(offset: np.ndarray, n_left: np.ndarray, n_right: np.ndarray) -> np.ndarray:
    """(3, 3) unit columns [d, n_left, n_right]: the directions that fix a pose from two contacts (paper Sec. 3.4)."""
    return np.stack([normalize(offset), normalize(n_left), normalize(n_right)], axis=1)


def dual_contact_conditioning(offset: np.ndarray, n_left: np.ndarray, n_right: np.ndarray) -> tuple[float, np.ndarray]:
    """sigma_2 / sigma_1 of [d, n_left, n_right] and its singular values: 0 when the three are parallel
    (near-coaxial contacts leave the rotation about that axis free)."""
    singular_values = np.linalg.svd(dual_contact_directions(offset, n_left, n_right), compute_uv=False)
    return float(singular_values[1] / singular_values[0]), singular_values


def validate_tactile_points(points: np.ndarray, source: str | Path | None) -> np.ndarray:
    """Check a tactile cloud is (N, 3), finite and large enough; return it as float64. Points whose three
    coordinates are all NaN are dropped: an organised cloud (one point per pixel, PCL's convention) marks the
    pixels without data so."""
    return _validated(points, source)[0]


def _validated(points: np.ndarray, source: str | Path | None) -> tuple[np.ndarray, GelReading]:
    """`validate_tactile_points`, and what the gel felt (`read_gel`), read once for the check and the contact."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"tactile cloud must be (N, 3), got shape {points.shape}", source)
    if not np.isfinite(points).all():
        points = points[~np.isnan(points).all(axis=1)]
        finite = np.isfinite(points).all(axis=1)
        if not finite.all():
            raise InputError(
                f"tactile cloud has {int((~finite).sum())} points with some coordinates NaN or inf (a point "
                "without data has all three NaN)",
                source,
            )
    if len(points) < MIN_TACTILE_POINTS:
        raise InputError(
            f"tactile cloud has only {len(points)} points; at least {MIN_TACTILE_POINTS} are needed to localize "
            "a contact",
            source,
        )
    extent = max(float(np.ptp(points[:, axis])) for axis in range(3))  # column by column: faster than axis=0
    if extent > 0.1:
        raise InputError(
            f"tactile cloud spans {extent * 1000:.0f} mm, larger than any GelSight pad: is it in metres and in the "
            "sensor frame?",
            source,
        )
    if extent < 1e-4:
        raise InputError(f"tactile cloud spans only {extent * 1e3:.3f} mm: it holds no contact surface", source)
    gel = read_gel(points)
    if not gel.pressed:
        hint = (
            " (are its z values flipped? SPEC: z <= 0 where the gel is pressed)"
            if read_gel(points * np.array([1.0, 1.0, -1.0])).pressed
            else ""
        )
        raise NoContactError(
            f"no contact: the tactile cloud is not pressed into the gel (its deepest points are "
            f"{max(gel.depth_m, 0.0) * 1e3:.3f} mm deep, within the {gel.floor_m * 1e3:.3f} mm noise floor of the "
            f"undeformed gel){hint}",
            source,
        )
    return points, gel


def read_tactile_cloud(path: Path) -> np.ndarray:
    """A tactile cloud file (PLY, sensor frame, metres), validated, and read as its contact when it covers the whole
    pad (`without_untouched_gel`). Errors name the file."""
    points, gel = _validated(read_ply_points(path)[0], path)
    points = gel.felt(points)
    if len(points) < MIN_TACTILE_POINTS:
        raise InputError(
            f"tactile cloud has only {len(points)} points pressed into the gel (the rest lie on the undeformed gel); "
            f"at least {MIN_TACTILE_POINTS} are needed to localize a contact",
            path,
        )
    return points


def without_untouched_gel(points_sensor: np.ndarray) -> np.ndarray:
    """The cloud's contact: without the untouched gel of a cloud of the whole pad (`read_gel`, `GelReading.felt`)."""
    return read_gel(points_sensor).felt(points_sensor)


@dataclass(frozen=True)
class GelReading:
    """What a tactile cloud says the gel felt (`read_gel`): how deep it is pressed, over what noise, and whether the
    cloud holds the untouched gel around the contact (the whole pad) or the contact's points alone."""

    depth_m: float  # the INDENTATION_POINTS-th deepest point's -z (a few spikes do not make a contact)
    noise_m: float  # 1 sigma of the heights' noise, from the points above the gel plane (0 when none lies there)
    whole_pad: bool  # the cloud holds the untouched gel around its contact

    @property
    def floor_m(self) -> float:
        """The depth above which a point may be the undeformed gel's noise."""
        return max(NO_INDENTATION_M, NOISE_MARGIN * self.noise_m)

    @property
    def pressed(self) -> bool:
        """Whether the cloud's deepest points lie beyond the noise floor: a flat noisy cloud on the gel plane is not,
        whether or not it is dense."""
        return self.depth_m > self.floor_m

    @property
    def contact_from_m(self) -> float:
        """The depth from which a whole pad's points are the object's: beyond the noise floor and SINK_IN_SHARE of the
        contact's depth (the ring where the gel sinks in around a contact without touching the object; a cloud of
        contact points alone, whose writer knew the contact, holds none)."""
        return max(self.floor_m, SINK_IN_SHARE * self.depth_m)

    @property
    def kiss(self) -> bool:
        """Whether the object only kisses the gel (its deepest points less than KISS_DEPTH_M deep), if it touches at
        all: a tracking frame so read shows the object leaving the gel. (The pose stage still matches such a side
        as a small contact, with the low belief of its area: `localize.scaled_match`.)"""
        return self.depth_m < KISS_DEPTH_M

    def felt(self, points_sensor: np.ndarray) -> np.ndarray:
        """The read cloud's contact points: a pressed whole pad's points deeper than `contact_from_m`; a cloud of
        contact points alone, or one not pressed (which holds no contact: `pressed`), as it is."""
        if not (self.pressed and self.whole_pad):
            return points_sensor
        pressed = points_sensor[:, 2] <= -self.contact_from_m
        if pressed.all() or pressed.sum() < INDENTATION_POINTS:
            return points_sensor
        return points_sensor[pressed]


def read_gel(points_sensor: np.ndarray) -> GelReading:
    """The one rule by which a tactile cloud is read as a contact (constants above; docs/journal/formats.md, stop 16):
    its depth, its noise and noise floor, whether it is pressed, and whether it holds the untouched gel."""
    z = points_sensor[:, 2]
    k = min(INDENTATION_POINTS, len(z))
    depth = float(-np.partition(z, k - 1)[k - 1]) if k else 0.0
    above = z[z > 0]
    noise = float(np.median(above)) / HALF_NORMAL_MEDIAN if len(above) else 0.0
    on_gel = int((z >= 0.0).sum())
    whole_pad = on_gel >= INDENTATION_POINTS and (on_gel >= UNTOUCHED_SHARE * len(z) or spans_the_pad(points_sensor))
    return GelReading(depth, noise, whole_pad)


def spans_the_pad(points_sensor: np.ndarray) -> bool:
    """Whether the cloud reaches across nine tenths of the GelSight Mini's pad both ways: a whole pad, even where its
    untouched gel lies a little below z = 0 (a reconstruction's offset) and only noise's tail reaches above."""
    width, height = MINI_PAD_M
    if len(points_sensor) == 0:
        return False
    return bool(np.ptp(points_sensor[:, 0]) > 0.9 * width and np.ptp(points_sensor[:, 1]) > 0.9 * height)


LARGEST_PLAUSIBLE_POSITION_M = 50.0  # a pose further from the world origin is most likely in millimetres


def _read_matrix(record: dict, key: str, what: str, path: Path) -> np.ndarray:
    if key not in record:
        raise InputError(f"missing key '{key}' in {what}", path)
    transform = validate_transform(record[key], f"{what}.{key}", path)
    distance = float(np.linalg.norm(transform[:3, 3]))
    if distance > LARGEST_PLAUSIBLE_POSITION_M:
        raise InputError(
            f"{what}.{key} is {distance:.0f} from the world origin: matrices are in metres (is it in millimetres?)",
            path,
        )
    return transform


def _read_point(record: dict, key: str, what: str, path: Path) -> np.ndarray:
    value = np.asarray(record.get(key), dtype=np.float64) if record.get(key) is not None else None
    if value is None or value.shape != (3,) or not np.all(np.isfinite(value)):
        raise InputError(f"{what}.{key} must be a list of 3 finite numbers", path)
    return value


def read_contact_pair(
    path: str | Path, images: ImageReconstructor | None = None, from_images: bool = False
) -> ContactPair:
    """Read and validate a pair file and its two tactile clouds. Errors name the file and the problem.

    A side's cloud is its `points` PLY, or the reconstruction of its GelSight `image` by `images` when it gives no
    points or when `from_images` is set. Raises NoContactError (an InputError) when a side shows no contact.
    """
    path = Path(path)
    payload = read_json(path)
    if not isinstance(payload, dict):
        raise InputError("a contact pair file must hold a JSON object", path)
    for key in ("object", *SIDES):
        if key not in payload:
            raise InputError(f"missing key '{key}' (a contact pair needs 'object', 'left' and 'right')", path)
    if not isinstance(payload["object"], str) or not payload["object"]:
        raise InputError("'object' must be the object's name", path)

    contacts = {side: _read_side(payload[side], side, path, images, from_images) for side in SIDES}

    pair = ContactPair(object_name=payload["object"], left=contacts["left"], right=contacts["right"], path=path)
    truth = payload.get("ground_truth")
    if truth is not None:
        if not isinstance(truth, dict):
            raise InputError("'ground_truth' must be an object", path)
        # Partial truth is kept: a labelling tool may know the contacts (p_object) and not the pose, or the reverse.
        if "T_world_object" in truth:
            pair.T_world_mesh_true = _read_matrix(truth, "T_world_object", "ground_truth", path)
        for side in SIDES:
            if f"{side}_p_object" in truth:
                pair.p_mesh_true[side] = _read_point(truth, f"{side}_p_object", "ground_truth", path)
    pair.extra = {key: value for key, value in payload.items() if key not in ("object", *SIDES, "ground_truth")}

    separation = np.linalg.norm(pair.left.T_world_sensor[:3, 3] - pair.right.T_world_sensor[:3, 3])
    if separation < 0.005:
        raise InputError(
            f"the two sensors are {separation * 1000:.1f} mm apart: two simultaneous contacts need distinct sensors",
            path,
        )
    return pair


def read_touch(
    path: str | Path, images: ImageReconstructor | None = None, from_images: bool = False
) -> tuple[TactileContact, str | None]:
    """A touch file: one more contact of one sensor (e.g. the re-touch `next_touch` suggested), written like one
    side of a pair file, `{"points": "touch.ply", "T_world_sensor": 4x4}` (or an `image`), optionally with
    `"sensor": "left"|"right"`. Returns the contact and the sensor it names (None when it names none)."""
    path = Path(path)
    payload = read_json(path)
    if not isinstance(payload, dict):
        raise InputError("a touch file must hold a JSON object", path)
    sensor = payload.get("sensor")
    if sensor is not None and sensor not in SIDES:
        raise InputError(f"'sensor' must be 'left' or 'right', got {sensor!r}", path)
    return _read_side(payload, sensor or "touch", path, images, from_images), sensor


def _read_side(
    record: Any, side: str, path: Path, images: ImageReconstructor | None, from_images: bool
) -> TactileContact:
    """One side of a pair file: its cloud (from `points`, or reconstructed from `image`) and sensor pose."""
    if not isinstance(record, dict) or not ("points" in record or "image" in record):
        raise InputError(f"'{side}' must be an object with 'points' (or 'image') and 'T_world_sensor'", path)
    T_world_sensor = _read_matrix(record, "T_world_sensor", side, path)
    image = None
    if "image" in record:
        optional = {
            key: _side_file(record, key, side, path) for key in ("background", "calibration") if record.get(key)
        }
        image = TactileImage(_side_file(record, "image", side, path), **optional)
    if "points" in record and not (from_images and image is not None):
        cloud_path = _side_file(record, "points", side, path)
        sigma = _read_depth_scale_sigma(record, side, path)
        return TactileContact(read_tactile_cloud(cloud_path), T_world_sensor, cloud_path, image, sigma)
    assert image is not None
    if images is None:
        raise InputError(
            f"'{side}' gives a GelSight image ({image.image.name}) and no points: reconstructing it needs the "
            "sensor's calibration (`yoto pose --calibration CAL`; in Python "
            "`read_contact_pair(path, images=ImageSides(CAL))`, ImageSides from yoto.sensor.pair_images, "
            '`ImageSides()` when every image side names its own "calibration")',
            path,
        )
    try:
        points, depth_scale_sigma = images(image)
    except NoContactError as exc:
        raise NoContactError(f"{side}: {exc.problem}", exc.path) from exc
    points = validate_tactile_points(points, image.image)
    return TactileContact(points, T_world_sensor, image.image, image, depth_scale_sigma)


def _read_depth_scale_sigma(record: dict, side: str, path: Path) -> float:
    """A side's `depth_scale_sigma`: written beside a cloud reconstructed from a GelSight image, so that the pose
    stage still estimates the cloud's depth scale when the pair is read back from its PLY (0 when absent)."""
    value = record.get("depth_scale_sigma", 0.0)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value < 1.0:
        raise InputError(f"{side}.depth_scale_sigma must be a number in [0, 1), got {value!r}", path)
    return float(value)


def _side_file(record: dict, key: str, side: str, path: Path) -> Path:
    """A side's file entry: a path relative to the pair file (or absolute); Windows separators are read as '/'."""
    value = record[key]
    if not isinstance(value, str) or not value.strip():
        raise InputError(f"{side}.{key} must be a file path relative to the pair file, got {value!r}", path)
    file = path.parent / value
    if not file.exists() and "\\" in value:
        file = path.parent / value.replace("\\", "/")
    return file


def write_contact_pair(path: str | Path, pair: ContactPair) -> Path:
    """Write a pair file and its two PLY clouds (named after the pair file) atomically.

    A side read from (or beside) a GelSight image keeps its `image`, `background` and `calibration` entries, as
    paths relative to the new pair file, and a cloud reconstructed from an image its `depth_scale_sigma`.
    """
    path = Path(path)
    stem = path.stem
    payload: dict[str, Any] = {"object": pair.object_name}
    for side in SIDES:
        contact = pair.contact(side)
        cloud_name = f"{stem}_{side}.ply"
        write_ply_points(path.parent / cloud_name, contact.points_sensor)
        payload[side] = {"points": cloud_name, "T_world_sensor": contact.T_world_sensor}
        if contact.depth_scale_sigma > 0:
            payload[side]["depth_scale_sigma"] = contact.depth_scale_sigma
        if contact.image is not None:
            for key in ("image", "background", "calibration"):
                file = getattr(contact.image, key)
                if file is not None:
                    payload[side][key] = os.path.relpath(Path(file).resolve(), path.parent.resolve())
    if pair.T_world_mesh_true is not None or pair.p_mesh_true:
        truth: dict[str, Any] = {} if pair.T_world_mesh_true is None else {"T_world_object": pair.T_world_mesh_true}
        for side in SIDES:
            if side in pair.p_mesh_true:
                truth[f"{side}_p_object"] = pair.p_mesh_true[side]
        payload["ground_truth"] = truth
    payload.update(pair.extra)
    return write_json_atomic(path, payload)


POSE_RESULT_SUFFIX = ".pose.json"
FOLDER_SETTINGS_FILE = "simulation.json"  # written by `yoto simulate pairs` beside its pair files


def is_pair_file_name(path: Path) -> bool:
    """Pair files are a folder's JSON files other than hidden files, pose results and the folder's settings."""
    name = path.name
    return not name.startswith(".") and not name.endswith(POSE_RESULT_SUFFIX) and name != FOLDER_SETTINGS_FILE


def find_pair_files(inputs: list[str | Path]) -> list[Path]:
    """Pair files from a list of files and folders (a folder contributes its `*.json`, sorted)."""
    found: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found.extend(sorted(p for p in item.glob("*.json") if is_pair_file_name(p)))
        elif item.is_file():
            found.append(item)
        else:
            raise InputError("no such file or folder", item)
    if not found:
        raise InputError(f"no contact pair files (*.json) in {', '.join(map(str, inputs))}")
    return found


__all__ = [
    "SIDES",
    "WELL_CONDITIONED",
    "ContactEstimate",
    "ContactPair",
    "GelReading",
    "ImageReconstructor",
    "TactileContact",
    "TactileImage",
    "WorldContact",
    "contact_in_sensor",
    "contact_in_world",
    "dual_contact_conditioning",
    "find_pair_files",
    "read_contact_pair",
    "read_gel",
    "read_tactile_cloud",
    "validate_tactile_points",
    "spans_the_pad",
    "without_untouched_gel",
    "write_contact_pair",
]
