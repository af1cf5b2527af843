"""The matched filter at a resolution that fits the contact: small contacts are matched, never refused.

The matched filter compares height maps of 1.5 mm cells over a 10.5 mm disc: right for the broad contacts of
curved surfaces, but a tip, a ridge or an edge (a figurine's ear, a blade) presses a patch of a millimetre or
less, which covers fewer than three cells and cannot be matched. Such a contact is matched with finer cells
over a smaller disc instead: each halving of the cell halves the disc, so every level has about as many cells
as the default, and the anchors are packed closer (`ScaleConfig`). The level is the coarsest whose cells the
contact covers `min_cells` times over. Its anchor maps are built the first time a contact needs them (seconds)
and cached like the default's. Candidates say which cell size found them (`match_cell_mm`). A small patch says
little about where it is (and a gel smooths a sharp tip into a dimple wider than the tip), so below the default
level the beliefs are scaled down by the contact's area: low, honest beliefs that the pose stage's confidence
carries, while the joint choice with the other contact can still pick the right candidate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from yoto.contacts import ContactEstimate, contact_in_sensor, validate_tactile_points
from yoto.errors import DegenerateGeometryError
from yoto.geometry import tangent_basis
from yoto.localize.match import AnchorConfig, AnchorMaps, MatchConfig, MatchLocalizer
from yoto.objects.model import ObjectModel
from yoto.tactile_image import tactile_spacing_m


@dataclass(frozen=True)
class ScaleConfig:
    """How the matched filter's resolution follows the contact's size."""

    min_cells: float = 4.0  # a level is used when the contact's area is at least this many of its coarse cells
    levels: int = 4  # finer levels below the default, each with half the cell size (1.5 mm -> 94 um)
    radius_cells: float = 7.0  # the height maps of a finer level cover a disc of this many cells' radius ...
    min_radius_m: float = 0.001  # ... and at least this radius (free space around a tip must be seen)
    anchor_spacing_m: float = 0.001  # anchors of the finer levels (the default's: 2 mm)
    area_pixel_m: float = 1e-4  # pixel of the occupancy grid that measures the contact's area


def contact_area_m2(points_sensor: np.ndarray, pixel_m: float) -> float:
    """Area the tactile cloud covers in its own tangent plane: occupied pixels of at least the cloud's spacing."""
    centre, normal = contact_in_sensor(points_sensor)
    u, v = tangent_basis(-normal)
    local = (points_sensor - centre) @ np.stack([u, v], axis=1)
    pixel = max(pixel_m, tactile_spacing_m(local))
    cells = np.floor(local / pixel).astype(np.int64)
    cells -= cells.min(axis=0)
    occupied = np.zeros(cells.max(axis=0) + 1, dtype=bool)
    occupied[cells[:, 0], cells[:, 1]] = True
    return int(np.count_nonzero(occupied)) * pixel * pixel


class ScaledMatchLocalizer:
    """The matched filter (`MatchLocalizer`), with finer height-map cells for contacts too small for the default."""

    name = "match"
    needs_ground_truth = False
    reads_depth_scale = True  # `localize` takes a reconstructed cloud's depth_scale_sigma (base.localize_cloud)

    def __init__(self, config: MatchConfig = MatchConfig(), scale: ScaleConfig = ScaleConfig()):
        self.config = config
        self.scale = scale
        self.default = MatchLocalizer(config)
        self._levels: dict[int, MatchLocalizer] = {0: self.default}

    def prepare_object(self, model: ObjectModel) -> AnchorMaps:
        """The default anchor maps (finer levels are built when a small contact first needs them)."""
        return self.default.prepare_object(model)

    def level_for(self, area_m2: float) -> int:
        """The coarsest level whose coarse cells (half of all, checkerboard) the contact covers `min_cells` times."""
        for level in range(self.scale.levels + 1):
            if area_m2 >= self.min_area_m2(level):
                return level
        return self.scale.levels

    def localizer(self, level: int) -> MatchLocalizer:
        """The matched filter of a level: cells of cell_m / 2^level, a disc of `radius_cells` of them."""
        if level not in self._levels:
            cell = self.config.anchors.cell_m / 2**level
            radius = max(self.scale.radius_cells * cell, self.scale.min_radius_m)
            spacing = min(self.config.anchors.anchor_spacing_m, self.scale.anchor_spacing_m)
            anchors: AnchorConfig = replace(
                self.config.anchors,
                cell_m=cell,
                map_radius_m=radius,
                anchor_spacing_m=spacing,
                nms_radius_m=min(self.config.anchors.nms_radius_m, max(2.0 * spacing, radius)),
            )
            config = replace(
                self.config,
                anchors=anchors,
                contact_pixel_m=min(self.config.contact_pixel_m, cell / 2.0),
                contact_erode_px=self.config.contact_erode_px if level <= 1 else 0,
                free_clearance_m=min(self.config.free_clearance_m, cell),
            )
            self._levels[level] = MatchLocalizer(config)
        return self._levels[level]

    def localize(
        self,
        points_sensor: np.ndarray,
        model: ObjectModel,
        truth_p_object: np.ndarray | None = None,
        depth_scale_sigma: float = 0.0,
    ) -> list[ContactEstimate]:
        """The matched filter's candidates at the level that fits the contact (a finer one if it is still too small).

        Below the default level the beliefs are scaled by the contact's area over the smallest area the default
        level matches: a small patch says little about where it is, and the pose stage's confidence shows it. A
        cloud reconstructed from an image (`depth_scale_sigma` > 0) is matched at several depth scales
        (`MatchLocalizer.localize_scaled`).
        """
        points_sensor = validate_tactile_points(points_sensor, None)
        localizer, area, candidates = self.default, None, None
        # Most contacts are broad: when the trusted pixels of the default level's image alone cover its smallest
        # area (they lie inside the contact, so they do not overstate it), that image is matched as it is and the
        # finer area measurement is skipped.
        image = self.default.image(points_sensor, model)
        if np.count_nonzero(image.mask) * image.pixel_m**2 >= self.min_area_m2(0):
            try:
                if self.default.scales_depth(depth_scale_sigma):
                    candidates = self.default.localize_scaled(points_sensor, model, image)
                else:
                    candidates = self.default.localize_image(image, model)
            except DegenerateGeometryError:
                pass
        if candidates is None:
            area = contact_area_m2(points_sensor, self.scale.area_pixel_m)
            level = self.level_for(area)
            while True:
                localizer = self.localizer(level)
                try:
                    candidates = localizer.localize(points_sensor, model, depth_scale_sigma=depth_scale_sigma)
                    break
                except DegenerateGeometryError:
                    if level >= self.scale.levels:
                        raise
                    level += 1  # the filter's own cover test is stricter than the area estimate: one level finer
        trust = min(1.0, area / self.min_area_m2(0)) if area is not None and localizer is not self.default else 1.0
        for candidate in candidates:
            candidate.probability *= trust
            candidate.details["match_cell_mm"] = 1000.0 * localizer.config.anchors.cell_m
        return candidates

    def min_area_m2(self, level: int) -> float:
        """The smallest contact area a level is chosen for."""
        return self.scale.min_cells * 2.0 * (self.config.anchors.cell_m / 2**level) ** 2
