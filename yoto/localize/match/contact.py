"""The contact's height image (yoto.tactile_image) with its free-space data, and that image sampled at every roll."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from yoto.localize.match.config import MatchConfig
from yoto.localize.match.kernels import KERNELS
from yoto.tactile_image import TactileHeightImage, binary_dilation, tactile_height_image


@dataclass
class ContactImage(TactileHeightImage):
    """The contact's height image (yoto.tactile_image), with what the free-space test needs."""

    touched: np.ndarray  # (S, S) pixels within the free-space clearance of the contact
    free_margin_m: float  # unseen surface may press the gel this deep without contradicting the contact

    def points_local(self) -> np.ndarray:
        """(M, 3) pixel centres of the trusted mask with their heights, local frame."""
        i, j = np.nonzero(self.mask)
        return np.stack(
            [(i + 0.5) * self.pixel_m - self.half_m, (j + 0.5) * self.pixel_m - self.half_m, self.heights[i, j]], axis=1
        )

    def to_sensor(self, local: np.ndarray) -> np.ndarray:
        return self.centre_sensor + local @ self.basis_sensor.T


def contact_image(points_sensor: np.ndarray, radius_m: float, config: MatchConfig) -> ContactImage:
    """The tactile cloud as a height image around its contact centre.

    Pixels are `contact_pixel_m`, or coarser when the cloud is sparser than that (clouds from other programs
    may be); single empty pixels inside the contact are filled from their neighbours, so sparse sampling
    does not punch holes that the rim erosion would widen.
    """
    image = tactile_height_image(points_sensor, radius_m, config.contact_pixel_m, config.contact_erode_px)
    pixel, filled = image.pixel_m, image.filled
    clearance = int(np.ceil(config.free_clearance_m / pixel))
    touched = binary_dilation(filled, clearance) if clearance > 0 else filled
    # A sensor may report only the deeper part of a contact (a reconstruction's mask keeps pixels pressed at
    # least some fraction of the deepest): surface pressing the gel less deep than the cloud's shallowest
    # points may lie where nothing was reported.
    shallowest = float(np.quantile(-points_sensor[:, 2], config.free_margin_quantile))
    free_margin = max(config.free_margin_m, shallowest + config.free_margin_m)
    return ContactImage(**vars(image), touched=touched, free_margin_m=free_margin)


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
    if KERNELS is not None:
        shape = (roll_count, len(centres))
        heights, mask = np.empty(shape, dtype=np.float32), np.empty(shape, dtype=np.float32)
        free, gel = np.empty(shape, dtype=bool), np.empty(shape, dtype=np.float32)
        pad_x, pad_y = np.asarray(config.pad_size_m) / 2.0
        KERNELS.sample_rolls(
            image.heights, image.mask, ~image.touched, image.half_m, image.pixel_m, np.cos(rolls), np.sin(rolls),
            np.ascontiguousarray(centres, dtype=np.float64), image.centre_sensor, image.basis_sensor, pad_x, pad_y,
            heights, mask, free, gel,
        )  # fmt: skip
        return ContactMaps(image=image, heights=heights, mask=mask, free=free, gel_heights=gel, rolls_rad=rolls)
    cos, sin = np.cos(rolls)[:, None], np.sin(rolls)[:, None]
    x = cos * centres[:, 0] + sin * centres[:, 1]  # Rz(-roll) applied to the cell centres
    y = -sin * centres[:, 0] + cos * centres[:, 1]
    heights, covered = image.sample(x, y, image.mask)
    near = image.covered(x, y, ~image.touched)
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
