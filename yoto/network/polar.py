"""Polar height maps: what the `cpu` network sees of a contact or of an anchor, and the roll search on them.

A contact and an anchor are both described by the surface's height around a centre point, in a frame whose z
axis points into the object along the surface normal (heights >= 0 on a convex surface), sampled at the centres
of polar cells: `rings` rings of `ring_width_m`, each cut into `angles` sectors. The sensor's roll about its axis
is unknown: rolling a contact only shifts every ring's samples along the ring, so the network's features
(yoto.network.descriptor) ignore it, and the fine stage finds it by trying every shift (`roll_plane_search`).

Both sides are point samples at the same positions: the tactile cloud is first binned into a fine height image
(mean height per pixel) that is read bilinearly at the cell centres, and anchors are ray cast at the cell centres
(yoto.network.anchors). Averaging a curved surface over a whole cell instead biases the heights of the outer,
larger cells, enough to rank the true anchor below wrong ones (docs/network.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy import ndimage

from yoto.network.presets import AnchorNetConfig
from yoto.sensor.spec import GELSIGHT_MINI
from yoto.tactile_image import tactile_height_image

MIN_PLANE_CELLS = 6  # fewer shared cells cannot support an offset-and-tilt fit (offset only then)
FREE_CLEARANCE_M = 0.0005  # cells this close to the contact are not judged free (its rim is uncertain)
FREE_MARGIN_M = 0.0001  # unseen surface may reach this far into the gel without contradicting the contact ...
FREE_MARGIN_QUANTILE = 0.02  # ... or as deep as the cloud's shallowest points (this quantile of their depth)


@dataclass(frozen=True)
class PolarGrid:
    """Polar cells around a centre: ring i spans radii [i w, (i + 1) w), sector t angles [t d, (t + 1) d)."""

    rings: int
    angles: int
    ring_width_m: float

    @classmethod
    def of(cls, config: AnchorNetConfig) -> PolarGrid:
        return cls(config.rings, config.angles, config.ring_width_m)

    @property
    def radius_m(self) -> float:
        return self.rings * self.ring_width_m

    @cached_property
    def centres(self) -> np.ndarray:
        """(R, T, 2) cell centres (x, y): radius (i + 0.5) w, angle (t + 0.5) 2 pi / T, counter-clockwise from +x."""
        radii = (np.arange(self.rings) + 0.5) * self.ring_width_m
        angles = (np.arange(self.angles) + 0.5) * 2.0 * np.pi / self.angles
        return np.stack([radii[:, None] * np.cos(angles)[None], radii[:, None] * np.sin(angles)[None]], axis=-1)

    @cached_property
    def weights(self) -> np.ndarray:
        """(R, T) cell areas in units of the innermost cell's: each sample stands for its cell's share of the disc."""
        return np.broadcast_to((2.0 * np.arange(self.rings) + 1.0)[:, None], (self.rings, self.angles)).copy()


@dataclass
class ContactPolarMap:
    """A tactile cloud's heights on the polar cells around its contact centre."""

    heights_m: np.ndarray  # (R, T) surface height into the object at each cell centre, relative to the centre (0: none)
    covered: np.ndarray  # (R, T) bool: the contact covers the cell centre
    centre_sensor: np.ndarray  # (3,) contact centre (yoto.contacts.contact_in_sensor)
    normal_sensor: np.ndarray  # (3,) outward object normal at the contact
    basis_sensor: np.ndarray  # (3, 3) columns u, v, z = -normal: the map's frame in the sensor frame
    pixel_m: float  # pixel of the height image the cells were read from
    free: np.ndarray  # (R, T) bool: cells over the sensor's pad, away from the contact: the object did not touch there
    gel_heights_m: np.ndarray  # (R, T) height of the undeformed gel plane (sensor z = 0) at each cell, map frame
    free_margin_m: float  # surface may reach this far past the gel plane at a free cell without contradiction

    def network_input(self, height_unit_m: float) -> np.ndarray:
        """(2, R, T) float32: heights in `height_unit_m` (0 off the contact) and coverage."""
        return np.stack([np.where(self.covered, self.heights_m / height_unit_m, 0.0), self.covered]).astype(np.float32)


def contact_polar_map(
    points_sensor: np.ndarray,
    grid: PolarGrid,
    pixel_m: float,
    erode_px: int,
    pad_size_m: tuple[float, float] = GELSIGHT_MINI.pad_size_m,
) -> ContactPolarMap:
    """Sample a tactile cloud (N, 3; sensor frame, metres) on the polar cells around its contact centre.

    The cloud becomes a height image in the contact's tangent frame (u as close to the sensor's x as it gets): mean
    height per pixel of `pixel_m`, or 1.5 x the cloud's own point spacing when it is sparser (clouds from other
    programs may be); single empty pixels are filled from their neighbours, and the rim is eroded by `erode_px`
    pixels (at the rim the gel, not the object, shapes the surface). A cell is covered when the four pixels around
    its centre are; its height is read bilinearly. A cell is free when it lies over the pad (`pad_size_m`, x and y
    extents, centred on the sensor axis) and no pixel within FREE_CLEARANCE_M of it holds points.
    """
    image = tactile_height_image(points_sensor, grid.radius_m, pixel_m, erode_px)
    centre, normal, basis, pixel = image.centre_sensor, image.normal_sensor, image.basis_sensor, image.pixel_m
    x, y = grid.centres[..., 0], grid.centres[..., 1]
    sampled, covered = image.sample(x, y, image.mask)
    # Free cells: over the pad (where the cell's line along the map's z meets the gel plane z_sensor = 0) and away
    # from every pixel the contact filled.
    clearance = int(np.ceil(FREE_CLEARANCE_M / pixel))
    near = ndimage.binary_dilation(image.filled, iterations=clearance) if clearance > 0 else image.filled
    gel = -(centre[2] + basis[2, 0] * x + basis[2, 1] * y) / basis[2, 2]
    on_gel = centre[:, None, None] + basis[:, 0, None, None] * x + basis[:, 1, None, None] * y
    on_gel = on_gel + basis[:, 2, None, None] * gel
    on_pad = (np.abs(on_gel[0]) <= pad_size_m[0] / 2) & (np.abs(on_gel[1]) <= pad_size_m[1] / 2)
    free = on_pad & ~near[image.pixel_of(x, y)]
    # A sensor may report only the deeper part of a contact: surface pressing the gel less deep than the cloud's
    # shallowest points may lie where nothing was reported.
    shallowest = float(np.quantile(-points_sensor[:, 2], FREE_MARGIN_QUANTILE))
    margin = max(FREE_MARGIN_M, shallowest + FREE_MARGIN_M)
    return ContactPolarMap(np.where(covered, sampled, 0.0), covered, centre, normal, basis, pixel, free, gel, margin)


def press_maps(heights_m: np.ndarray, valid: np.ndarray, depth_m: float, height_unit_m: float) -> np.ndarray:
    """(A, 2, R, T) float32 network inputs of surface height maps (A, R, T): the cells a press `depth_m` deep along
    the normal would touch (within `depth_m` of the surface nearest the pad, which is at most the centre's height 0),
    with their heights in `height_unit_m`, as a contact of that press would show them."""
    nearest = np.minimum(np.where(valid, heights_m, np.inf).min(axis=(1, 2), keepdims=True), 0.0)
    touched = valid & (heights_m <= nearest + depth_m)
    return np.stack([np.where(touched, heights_m / height_unit_m, 0.0), touched], axis=1).astype(np.float32)


@dataclass
class RollFit:
    """The best roll and plane of a contact against each of N surface height maps."""

    cost_m2: np.ndarray  # (N,) weighted mean squared height difference at the best roll (with the air penalty)
    shift: np.ndarray  # (N,) int: the best roll is shift * 2 pi / angles (map angle = contact angle + roll)
    plane: np.ndarray  # (3, N) offset, x slope, y slope of (contact height - map height) in the contact's frame


def roll_plane_search(
    contact: ContactPolarMap, grid: PolarGrid, heights_m: np.ndarray, valid: np.ndarray, air_penalty_m: float
) -> RollFit:
    """Fit the contact to each surface height map (N, R, T) at every roll: least squares over the cells both cover,
    after removing the best plane (offset and tilt: a slightly misjudged normal), area-weighted; contact cells where
    the map has no surface cost `air_penalty_m` squared each. Returns each map's best roll and its plane.

    The roll moves the map's samples along the rings, so every sum over cells, for all rolls at once, is a circular
    cross-correlation along the angle (one FFT product per sum): a contact term (R, T) against a map term (N, R, T).
    `roll_plane_search_reference` computes the same with an explicit loop and least-squares solve.
    """
    h = contact.heights_m
    w = grid.weights * contact.covered
    x, y = grid.centres[..., 0], grid.centres[..., 1]
    maps = {
        "v": valid.astype(np.float64),
        "vh": np.where(valid, heights_m, 0.0).astype(np.float64),
    }
    maps["vhh"] = maps["vh"] * maps["vh"]
    spectra = {key: np.fft.rfft(value, axis=-1) for key, value in maps.items()}

    def correlate(contact_term: np.ndarray, map_key: str) -> np.ndarray:
        """(N, T) sum over cells of contact_term(cell) * map term(cell rolled by each shift)."""
        product = np.conj(np.fft.rfft(contact_term, axis=-1))[None] * spectra[map_key]
        return np.fft.irfft(product.sum(axis=1), n=grid.angles, axis=-1)

    n = correlate(w, "v")
    sx, sy = correlate(w * x, "v"), correlate(w * y, "v")
    sxx, sxy, syy = correlate(w * x * x, "v"), correlate(w * x * y, "v"), correlate(w * y * y, "v")
    # Moments of d = (contact height - map height) against the plane's basis functions 1, x, y.
    b0 = correlate(w * h, "v") - correlate(w, "vh")
    b1 = correlate(w * h * x, "v") - correlate(w * x, "vh")
    b2 = correlate(w * h * y, "v") - correlate(w * y, "vh")
    sdd = correlate(w * h * h, "v") - 2.0 * correlate(w * h, "vh") + correlate(w, "vhh")
    # Normal equations G beta = b, G = [[n, sx, sy], [sx, sxx, sxy], [sy, sxy, syy]], by cofactors.
    c00, c01, c02 = sxx * syy - sxy * sxy, sy * sxy - sx * syy, sx * sxy - sy * sxx
    c11, c12, c22 = n * syy - sy * sy, sx * sy - n * sxy, n * sxx - sx * sx
    det = n * c00 + sx * c01 + sy * c02
    spread = sxx + syy
    # A plane needs shared cells spread in two directions: det is ~ n (second moments)^2 when it is well posed.
    solvable = (n >= MIN_PLANE_CELLS) & (det > 1e-2 * n * spread * spread / 4.0)
    inverse = np.where(solvable, 1.0 / np.where(solvable, det, 1.0), 0.0)
    plane = np.stack(
        [
            (c00 * b0 + c01 * b1 + c02 * b2) * inverse,
            (c01 * b0 + c11 * b1 + c12 * b2) * inverse,
            (c02 * b0 + c12 * b1 + c22 * b2) * inverse,
        ]
    )
    safe_n = np.maximum(n, 1e-9)
    sse = np.where(solvable, sdd - (plane[0] * b0 + plane[1] * b1 + plane[2] * b2), sdd - b0 * b0 / safe_n)
    plane[0] = np.where(solvable, plane[0], b0 / safe_n)
    plane[1:] = np.where(solvable, plane[1:], 0.0)
    total = max(float(w.sum()), 1e-9)
    cost = (np.maximum(sse, 0.0) + air_penalty_m**2 * np.maximum(total - n, 0.0)) / total
    shift = np.argmin(cost, axis=1)
    rows = np.arange(len(shift))
    return RollFit(cost[rows, shift], shift, plane[:, rows, shift])


def free_space_penalty(
    contact: ContactPolarMap,
    grid: PolarGrid,
    heights_m: np.ndarray,
    valid: np.ndarray,
    fit: RollFit,
    cap_m: float,
) -> np.ndarray:
    """(N,) how far each map's surface, placed by its fit, would push into the gel where the sensor saw nothing:
    the area-weighted sum over free cells of the squared depth past the gel plane (less the margin, capped at
    `cap_m`), over the contact's total weight, so it adds to the fit's mean squared height difference."""
    rows = np.arange(len(fit.shift))[:, None]
    angles = (np.arange(grid.angles)[None] + fit.shift[:, None]) % grid.angles  # (N, T) map sector of each cell
    rolled_h = heights_m[rows, :, angles].transpose(0, 2, 1)  # (N, R, T)
    rolled_v = valid[rows, :, angles].transpose(0, 2, 1)
    x, y = grid.centres[..., 0], grid.centres[..., 1]
    surface = rolled_h + fit.plane[0][:, None, None] + fit.plane[1][:, None, None] * x + fit.plane[2][:, None, None] * y
    depth = np.minimum(contact.gel_heights_m - contact.free_margin_m - surface, cap_m)
    judged = contact.free[None] & rolled_v
    penalty = (grid.weights * np.where(judged, np.maximum(depth, 0.0) ** 2, 0.0)).sum(axis=(1, 2))
    return penalty / max(float((grid.weights * contact.covered).sum()), 1e-9)


def roll_plane_search_reference(
    contact: ContactPolarMap, grid: PolarGrid, heights_m: np.ndarray, valid: np.ndarray, air_penalty_m: float
) -> RollFit:
    """The slow, obvious version of `roll_plane_search` (tests): every map, every shift, a weighted lstsq."""
    x, y = grid.centres[..., 0].ravel(), grid.centres[..., 1].ravel()
    w_contact = (grid.weights * contact.covered).ravel()
    total = max(float(w_contact.sum()), 1e-9)
    costs = np.zeros((len(heights_m), grid.angles))
    planes = np.zeros((3, len(heights_m), grid.angles))
    for i in range(len(heights_m)):
        for shift in range(grid.angles):
            rolled_h = np.roll(heights_m[i], -shift, axis=1).ravel()  # cell t of the contact meets cell t + shift
            rolled_v = np.roll(valid[i], -shift, axis=1).ravel()
            w = w_contact * rolled_v
            d = contact.heights_m.ravel() - rolled_h
            basis = np.stack([np.ones_like(x), x, y], axis=1)
            gram = basis.T @ (w[:, None] * basis)
            spread = gram[1, 1] + gram[2, 2]
            if gram[0, 0] >= MIN_PLANE_CELLS and np.linalg.det(gram) > 1e-2 * gram[0, 0] * spread * spread / 4.0:
                sqrt_w = np.sqrt(w)[:, None]
                beta = np.linalg.lstsq(basis * sqrt_w, d * sqrt_w[:, 0], rcond=None)[0]
            else:
                beta = np.array([(w * d).sum() / max(w.sum(), 1e-9), 0.0, 0.0])
            residual = d - basis @ beta
            costs[i, shift] = ((w * residual**2).sum() + air_penalty_m**2 * (total - w.sum())) / total
            planes[:, i, shift] = beta
    shift = np.argmin(costs, axis=1)
    rows = np.arange(len(shift))
    return RollFit(costs[rows, shift], shift, planes[:, rows, shift])
