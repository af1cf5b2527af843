"""The tactile cloud as a height image in its own tangent frame, and that image sampled at every roll."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from yoto.contacts import contact_in_sensor
from yoto.errors import DegenerateGeometryError
from yoto.geometry import tangent_basis
from yoto.localize.match.config import MatchConfig


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
        heights = np.zeros(np.shape(wx))
        for i, j, w in corners:
            heights += self.heights[i, j] * w
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
    """Median in-plane distance between neighbouring tactile points (the cloud's own resolution), measured on the
    `samples` points nearest the contact centre, their neighbours found among the 4 x `samples` nearest."""
    radial = local[:, 0] ** 2 + local[:, 1] ** 2
    near = np.argpartition(radial, min(4 * samples, len(local)) - 1)[: 4 * samples]
    near = near[np.argsort(radial[near])]
    distances, _ = cKDTree(local[near, :2]).query(local[near[:samples], :2], k=2)
    return float(np.median(distances[:, 1]))


def contact_image(points_sensor: np.ndarray, radius_m: float, config: MatchConfig) -> ContactImage:
    """The tactile cloud as a height image around its contact centre.

    Pixels are `contact_pixel_m`, or coarser when the cloud is sparser than that (clouds from other programs
    may be); single empty pixels inside the contact are filled from their neighbours, so sparse sampling
    does not punch holes that the rim erosion would widen.
    """
    centre, normal = contact_in_sensor(points_sensor)
    z_local = -normal
    u, v = tangent_basis(z_local, reference=np.array([1.0, 0.0, 0.0]))  # u as close to the image's x as it gets
    basis = np.stack([u, v, z_local], axis=1)
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


def contact_maps(image: ContactImage, centres: np.ndarray, roll_count: int, config: MatchConfig) -> ContactMaps:
    """Sample the contact image at the cell centres (C, 2) of every roll: anchor local = Rz(roll) contact local."""
    rolls = np.arange(roll_count) * (2.0 * np.pi / roll_count)
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
