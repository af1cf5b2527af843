"""The matched filter's depth-scale nuisance: a contact reconstructed from an image is matched at several depth
scales (MatchConfig.image_depth_scales); a clean cloud is matched as before."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("open3d")

from yoto.contacts import ContactEstimate  # noqa: E402
from yoto.errors import InputError  # noqa: E402
from yoto.localize.base import localize_cloud  # noqa: E402
from yoto.localize.match import MatchConfig, MatchLocalizer  # noqa: E402
from yoto.localize.scaled_match import ScaledMatchLocalizer  # noqa: E402
from yoto.simulate.scenarios import PairSimulator  # noqa: E402

READ_SHALLOW = 0.85  # a reconstruction that reads the contact's heights 15% shallow


def test_a_contact_read_shallow_is_placed_right_at_its_depth_scale(fruit_contacts):
    """Heights read 15% shallow make a bump look like a flatter one elsewhere: the filter alone puts at most one of
    six such contacts first at its true place, with the depth-scale nuisance (1.0 / 1.1 / 1.2) five or more, each
    first candidate found at a scale above 1."""
    model, contacts = fruit_contacts
    localizer = MatchLocalizer()
    plain = nuisance = 0
    for points_sensor, p_true, _ in contacts:
        shallow = points_sensor * np.array([1.0, 1.0, READ_SHALLOW])
        first = localizer.localize(shallow, model)[0]
        plain += bool(np.linalg.norm(first.p_object - p_true) < 2.5e-3)
        first = localizer.localize(shallow, model, depth_scale_sigma=0.05)[0]
        if np.linalg.norm(first.p_object - p_true) < 2.5e-3:
            nuisance += 1
            assert first.details["match_depth_scale"] > 1.0
    assert plain <= 1 and nuisance >= 5


def test_a_clean_cloud_is_matched_as_before(fruit_contacts):
    """Without a depth-scale sigma (a clean cloud), or with the nuisance off, the candidates are the plain
    filter's, bitwise; `localize_cloud` passes the sigma only to a localizer that reads it."""
    model, contacts = fruit_contacts
    points_sensor, _, _ = contacts[0]
    plain = MatchLocalizer(MatchConfig(image_depth_scales=(1.0,)))
    reference = plain.localize(points_sensor, model, depth_scale_sigma=0.05)
    for candidates in (
        MatchLocalizer().localize(points_sensor, model),
        ScaledMatchLocalizer().localize(points_sensor, model, depth_scale_sigma=0.0),
        localize_cloud(ScaledMatchLocalizer(), points_sensor, model),
    ):
        assert len(candidates) == len(reference)
        for got, want in zip(candidates, reference, strict=True):
            assert np.array_equal(got.p_object, want.p_object) and got.probability == want.probability
            assert got.details["match_T_object_sensor"] == want.details["match_T_object_sensor"]
            assert "match_depth_scale" not in got.details
    scaled = localize_cloud(ScaledMatchLocalizer(), points_sensor, model, depth_scale_sigma=0.05)
    assert {c.details["match_depth_scale"] for c in scaled} <= {1.0, 1.1, 1.2}

    class Fixed:  # a localizer without the depth-scale argument
        name, needs_ground_truth = "fixed", False

        def localize(self, points_sensor, model, truth_p_object=None):
            return [ContactEstimate(np.zeros(3), np.array([0.0, 0.0, 1.0]))]

    assert len(localize_cloud(Fixed(), points_sensor, model, depth_scale_sigma=0.05)) == 1


def test_the_pipeline_tells_the_localizer_which_contacts_come_from_images(builtin_models):
    """`localize_contacts` passes each side's `depth_scale_sigma` to a localizer that reads it, and only where it is
    positive (a clean side is localized as before)."""
    from dataclasses import replace

    from yoto.pose.pipeline import localize_contacts

    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=0).pair
    pair = replace(pair, right=replace(pair.right, depth_scale_sigma=0.05))
    seen = []

    class Recording:
        name, needs_ground_truth, reads_depth_scale = "recording", False, True

        def localize(self, points_sensor, model, truth_p_object=None, **keywords):
            seen.append(keywords)
            return [ContactEstimate(np.zeros(3), np.array([0.0, 0.0, 1.0]))]

    localize_contacts(pair, model, Recording())
    assert seen == [{}, {"depth_scale_sigma": 0.05}]


def test_depth_scales_must_be_positive():
    for scales in ((), (1.0, 0.0)):
        with pytest.raises(InputError, match="image_depth_scales"):
            MatchConfig(image_depth_scales=scales)
