"""Virtual GelSight contacts for the `cpu` network: a rigid pad ray cast into the object mesh.

The paper pre-trains on virtual patches cut from the object model. The `cpu` network reads a contact as a height
map (yoto.network.polar), so its virtual contacts must look like a sensor's: a dense grid of surface points over
the pad. Per contact, following the SPEC's description of a press: a target parent point, a pressing direction
within `max_tilt_deg` of its reversed normal, a random roll, the pad centre up to `max_offset_m` from the target,
an indentation depth in `depth_m`. Rays on a `pixel_m` grid over the pad find the surface; the contact is the
surface within the depth of the point nearest the pad, and its true location the surface point at its centre
(where the target lies outside the contact, a concavity, the contact is kept: it is elsewhere, and labelled so).
Then errors a reconstruction makes: a depth scale error, a tilted offset plane, per-point noise. The cloud goes
through the same polar sampling as a real contact.

This is a rigid pad on a bare mesh: no gel sinking in around the contact, no check that the sensor body fits, no
image reconstruction. It shares no code with the contact simulator (yoto.simulate) that benchmarks grade on; the
second training stage, on 20 contacts of the sensor (or of the simulator standing in for it), bridges the gap.
Stored per object in WORKSPACE/patches/NAME.contacts.npz: the network inputs and the true contact locations.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from yoto.contacts import contact_in_sensor
from yoto.errors import DegenerateGeometryError, InputError
from yoto.geometry import normalize, rotation_about_axis
from yoto.io import load_npz, save_npz_atomic
from yoto.network.polar import PolarGrid, contact_polar_map
from yoto.network.presets import AnchorNetConfig
from yoto.objects.model import ObjectModel
from yoto.sensor.spec import GELSIGHT_MINI
from yoto.workspace import patch_dataset_path

log = logging.getLogger("yoto")

FORMAT_NAME = "yoto-virtual-contacts"
GENERATOR_VERSION = 1  # bump when the generator changes what it makes (stored sets are then regenerated)


@dataclass(frozen=True)
class VirtualContactConfig:
    """How virtual contacts are drawn."""

    count: int = 12_000  # contacts per object
    depth_m: tuple[float, float] = (0.0005, 0.0015)  # indentation depth, uniform (SPEC: typically 0.5-1.5 mm)
    max_tilt_deg: float = 10.0  # pressing direction within this angle of the reversed surface normal
    max_offset_m: float = 0.0015  # the pad centre lies up to this far from the target, uniform on a disc
    pad_size_m: tuple[float, float] = GELSIGHT_MINI.pad_size_m  # sensed area (x, y)
    pixel_m: float = 0.00013  # spacing of the rays over the pad (the virtual sensor's pixel)
    min_points: int = 120  # fewer contact points (about 2 mm^2) are rejected
    scale_error: float = 0.1  # heights scaled by a factor uniform in 1 +- this
    plane_error_m: float = 2e-5  # a random plane added to the heights: offset and slope over 1 cm, each N(0, this)
    noise_m: float = 1e-5  # white height noise per point
    seed: int = 0


@dataclass
class VirtualContacts:
    """One object's virtual contacts as network inputs."""

    maps: np.ndarray  # (n, 2, R, T) float32 polar maps (yoto.network.polar.ContactPolarMap.network_input)
    p_object: np.ndarray  # (n, 3) true contact locations, object frame
    meta: dict  # config, network input settings, model fingerprint, rejections

    def __len__(self) -> int:
        return len(self.p_object)


def _press_direction(normal: np.ndarray, max_tilt_rad: float, rng: np.random.Generator) -> np.ndarray:
    """The reversed normal tilted by an angle uniform on the spherical cap of half-angle `max_tilt_rad`."""
    axis = np.cross(normal, rng.normal(size=3))
    angle = float(np.arccos(rng.uniform(np.cos(max_tilt_rad), 1.0)))
    return rotation_about_axis(axis, angle) @ (-normal) if np.linalg.norm(axis) > 1e-9 else -normal


def press_cloud(
    model: ObjectModel, target: np.ndarray, rng: np.random.Generator, config: VirtualContactConfig
) -> tuple[np.ndarray, np.ndarray] | str:
    """A noise-free virtual contact aimed at `target`: (points (N, 3) in its sensor frame, T_object_sensor (4, 4)),
    or the reason it was rejected. Sensor frame as the SPEC's: z toward the object, gel at z = 0, contact z <= 0."""
    normal = model.aggregated_normal(target, 20)
    z_axis = _press_direction(normal, np.radians(config.max_tilt_deg), rng)  # the direction the sensor moves
    x_axis = normalize(np.cross(z_axis, rng.normal(size=3)))
    y_axis = np.cross(z_axis, x_axis)
    radius = np.sqrt(rng.uniform()) * config.max_offset_m
    angle = rng.uniform(0.0, 2.0 * np.pi)
    pad_centre = target + radius * (np.cos(angle) * x_axis + np.sin(angle) * y_axis)
    half_x, half_y = config.pad_size_m[0] / 2, config.pad_size_m[1] / 2
    xs = np.arange(-half_x + config.pixel_m / 2, half_x, config.pixel_m)
    ys = np.arange(-half_y + config.pixel_m / 2, half_y, config.pixel_m)
    grid_x, grid_y = (g.ravel() for g in np.meshgrid(xs, ys, indexing="ij"))
    back_off = 2.0 * model.mesh_scale_m  # rays start outside the object
    origins = pad_centre + grid_x[:, None] * x_axis + grid_y[:, None] * y_axis - back_off * z_axis
    hits = model.raycaster.cast(origins, z_axis)
    if (hits.back_face & hits.hit).any():
        return "back_face"
    depth_along = hits.t_hit - back_off  # surface position along z from the pad-centre plane
    if not hits.hit.any():
        return "no_contact"
    nearest = depth_along[hits.hit].min()
    depth = rng.uniform(*config.depth_m)
    contact = hits.hit & (depth_along <= nearest + depth)
    if contact.sum() < config.min_points:
        return "small_contact"
    gel_plane = nearest + depth
    points = np.stack([grid_x[contact], grid_y[contact], depth_along[contact] - gel_plane], axis=1)
    T_object_sensor = np.eye(4)
    T_object_sensor[:3, :3] = np.stack([x_axis, y_axis, z_axis], axis=1)
    T_object_sensor[:3, 3] = pad_centre + gel_plane * z_axis
    return points, T_object_sensor


def reconstruction_errors(points: np.ndarray, rng: np.random.Generator, config: VirtualContactConfig) -> np.ndarray:
    """The cloud with a depth scale error, a random tilted offset and white noise on its heights."""
    noisy = points.copy()
    noisy[:, 2] *= 1.0 + rng.uniform(-config.scale_error, config.scale_error)
    plane = rng.normal(size=3) * config.plane_error_m
    noisy[:, 2] += plane[0] + (plane[1] * noisy[:, 0] + plane[2] * noisy[:, 1]) / 0.01
    noisy[:, 2] += rng.normal(size=len(noisy)) * config.noise_m
    return noisy


def generate_virtual_contacts(
    model: ObjectModel, network: AnchorNetConfig, config: VirtualContactConfig, progress: bool = False
) -> VirtualContacts:
    """`config.count` virtual contacts of `model` as network inputs (deterministic for the config's seed)."""
    rng = np.random.default_rng([config.seed, 4242])
    grid = PolarGrid.of(network)
    maps: list[np.ndarray] = []
    locations: list[np.ndarray] = []
    rejections: dict[str, int] = {}
    attempts = 0
    bar = tqdm(total=config.count, desc=f"{model.name}: virtual contacts", unit="contact", disable=not progress)
    while len(maps) < config.count and attempts < 5 * config.count:
        attempts += 1
        target = model.points_object[rng.integers(len(model.points_object))].astype(np.float64)
        pressed = press_cloud(model, target, rng, config)
        if isinstance(pressed, str):
            rejections[pressed] = rejections.get(pressed, 0) + 1
            continue
        points, T_object_sensor = pressed
        try:
            polar = contact_polar_map(
                reconstruction_errors(points, rng, config), grid, network.contact_pixel_m, network.contact_erode_px
            )
        except DegenerateGeometryError:
            rejections["degenerate"] = rejections.get("degenerate", 0) + 1
            continue
        centre_sensor, _ = contact_in_sensor(points)
        centre_object = T_object_sensor[:3, :3] @ centre_sensor + T_object_sensor[:3, 3]
        maps.append(polar.network_input(network.height_unit_m))
        locations.append(model.raycaster.closest_points(centre_object))
        bar.update(1)
    bar.close()
    if not maps:
        raise InputError(f"no virtual contact could be made on {model.name!r} (rejections: {rejections})")
    meta = {
        "format": FORMAT_NAME,
        "generator_version": GENERATOR_VERSION,
        "config": _plain(asdict(config)),
        "network_inputs": _input_settings(network),
        "fingerprint": model.fingerprint,
        "rejections": rejections,
        "attempts": attempts,
    }
    return VirtualContacts(np.asarray(maps, dtype=np.float32), np.asarray(locations), meta)


def _input_settings(network: AnchorNetConfig) -> dict:
    """The network settings that shape its inputs (a stored set made under other ones is regenerated)."""
    keys = ("rings", "angles", "ring_width_m", "height_unit_m", "contact_pixel_m", "contact_erode_px")
    return {key: getattr(network, key) for key in keys}


def _plain(values: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in values.items()}


def virtual_contacts_path(name: str, workspace: str | Path | None = None) -> Path:
    return patch_dataset_path(name, workspace).with_name(f"{name}.contacts.npz")


def virtual_contacts(
    model: ObjectModel,
    network: AnchorNetConfig,
    config: VirtualContactConfig,
    workspace: str | Path | None = None,
    progress: bool = False,
) -> VirtualContacts:
    """The virtual contacts of `model`: loaded when an up-to-date file exists, else generated and saved."""
    path = virtual_contacts_path(model.name, workspace)
    if path.exists():
        try:
            arrays, meta = load_npz(path, "virtual contacts")
            if (
                meta.get("format") == FORMAT_NAME
                and meta.get("generator_version") == GENERATOR_VERSION
                and meta.get("config") == _plain(asdict(config))
                and meta.get("network_inputs") == _input_settings(network)
                and meta.get("fingerprint") == model.fingerprint
            ):
                return VirtualContacts(arrays["maps"], arrays["p_object"], meta)
            log.info("%s: made for other settings or another build of %s; regenerating", path, model.name)
        except (InputError, KeyError) as exc:
            log.info("%s: regenerating (%s)", path, exc)
    contacts = generate_virtual_contacts(model, network, config, progress)
    save_npz_atomic(path, {"maps": contacts.maps, "p_object": contacts.p_object}, contacts.meta)
    log.info(
        "%s: %d virtual contacts in %d attempts (rejections %s)",
        model.name,
        len(contacts),
        contacts.meta["attempts"],
        contacts.meta["rejections"],
    )
    return contacts
