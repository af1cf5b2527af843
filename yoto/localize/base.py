"""The localizer interface: a tactile cloud in, ranked contact locations on the object model out.

Every method (the oracle, the ICP baseline, the YOTO network) implements `ContactLocalizer`, so the pose
pipeline and the benchmark swap them freely.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from yoto.contacts import ContactEstimate
from yoto.objects.model import ObjectModel


class ContactLocalizer(Protocol):
    """Locates one tactile contact on an object model."""

    name: str  # short method name used in result files and benchmark tables
    needs_ground_truth: bool  # True only for the oracle

    def localize(
        self, points_sensor: np.ndarray, model: ObjectModel, truth_p_object: np.ndarray | None = None
    ) -> list[ContactEstimate]:
        """Candidate contacts on `model` (object frame), best first; at least one.

        `points_sensor` is the tactile cloud (N, 3) in the sensor frame. `truth_p_object` is given only to
        localizers with `needs_ground_truth`.
        """
        ...


def localize_cloud(
    localizer: ContactLocalizer,
    points_sensor: np.ndarray,
    model: ObjectModel,
    truth_p_object: np.ndarray | None = None,
    depth_scale_sigma: float = 0.0,
) -> list[ContactEstimate]:
    """`localizer.localize` of a tactile cloud; a cloud reconstructed from an image (`depth_scale_sigma` > 0, as
    `TactileContact.depth_scale_sigma`) tells a localizer that matches over depth scales (`reads_depth_scale`:
    the matched filter) so."""
    if depth_scale_sigma > 0 and getattr(localizer, "reads_depth_scale", False):
        return localizer.localize(points_sensor, model, truth_p_object, depth_scale_sigma=depth_scale_sigma)  # type: ignore[call-arg]
    return localizer.localize(points_sensor, model, truth_p_object)


class OracleLocalizer:
    """The ground-truth contact location with its kNN-aggregated model normal: shows the solver's own floor."""

    name = "oracle"
    needs_ground_truth = True

    def __init__(self, normal_neighbours: int = 20):
        self.normal_neighbours = normal_neighbours

    def localize(
        self, points_sensor: np.ndarray, model: ObjectModel, truth_p_object: np.ndarray | None = None
    ) -> list[ContactEstimate]:
        if truth_p_object is None:
            raise ValueError("the oracle needs the ground-truth contact location")
        p_object = np.asarray(truth_p_object, dtype=np.float64)
        return [
            ContactEstimate(
                p_object=p_object,
                n_object=model.aggregated_normal(p_object, self.normal_neighbours),
                block=int(model.block_of_points(p_object)[0]),
                score=1.0,
                probability=1.0,
            )
        ]
