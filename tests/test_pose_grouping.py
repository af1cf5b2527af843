"""Grouping refined poses into hypotheses: the fast grouping (every pair's closeness at once, rotations compared by
their cosines) against its definition, every founder absorbing every unassigned pose within both distances of it."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TOL

from yoto.geometry import make_transform, random_rotations, rotation_about_axis, rotation_angle_rad, se3_exp
from yoto.objects.symmetry import Symmetry
from yoto.pose import hypotheses
from yoto.pose.hypotheses import (
    HypothesisConfig,
    _close_pairs,
    family_mean,
    group_hypotheses,
    log_likelihoods,
    pose_distances,
)
from yoto.pose.refine import Refined

SYMMETRIES = [
    Symmetry(),
    Symmetry(rotations=np.array([np.eye(3), rotation_about_axis(np.array([1.0, 0, 0]), np.pi)])),
    Symmetry(axis_object=np.array([0, 0, 1.0])),
    Symmetry(  # a can: turns about z, and turned over
        axis_object=np.array([0, 0, 1.0]),
        rotations=np.array([np.eye(3), rotation_about_axis(np.array([1.0, 0, 0]), np.pi)]),
    ),
    Symmetry(rotations=np.array([rotation_about_axis(np.array([0, 0, 1.0]), a) for a in np.arange(6) * np.pi / 3])),
]
IDS = ["none", "flip", "continuous", "can", "six-fold"]


def _grouped_by_definition(refined: Refined, symmetry: Symmetry, config: HypothesisConfig):
    """Members and supports of the greedy grouping, every pose's distance to every founder computed."""
    order = np.argsort(-log_likelihoods(refined, config), kind="stable")
    unassigned = np.ones(len(order), dtype=bool)
    members, support = [], []
    for k in order:
        if unassigned[k]:
            translation, rotation = pose_distances(refined.T_world_object, refined.T_world_object[k], symmetry)
            close = unassigned & (translation <= config.distinct_translation_m)
            close &= rotation <= config.distinct_rotation_rad
            close[k] = True
            unassigned &= ~close
            members.append(k)
            support.append(int(close.sum()))
    return np.array(members), np.array(support)


PATHS = ["compiled", "numpy"]


def _take_path(path: str, monkeypatch: pytest.MonkeyPatch) -> None:
    if path == "numpy":
        monkeypatch.setattr(hypotheses, "SEARCH_KERNELS", None)
    elif hypotheses.SEARCH_KERNELS is None:
        pytest.skip("no numba kernels (the `fast` extra not installed, or YOTO_NO_NUMBA set)")


def _refined(poses: np.ndarray, rng: np.random.Generator) -> Refined:
    """Refined poses with random fits (the grouping's order)."""
    count = len(poses)
    return Refined(
        poses,
        np.zeros((count, 2, 6)),
        rng.uniform(2e-5, 8e-5, size=(count, 2)),
        np.ones((count, 2)),
        np.zeros((count, 2)),
        np.zeros(count),
        np.zeros((count, 6)),
    )


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("symmetry", SYMMETRIES, ids=IDS)
def test_grouping_matches_its_definition(symmetry, path, rng, monkeypatch):
    _take_path(path, monkeypatch)
    # Clusters of poses a few millimetres and degrees around a few centres: many lie within the distinct
    # distances of one another in translation but not in rotation, and the other way round.
    centres = [make_transform(rotation, rng.normal(scale=0.01, size=3)) for rotation in random_rotations(rng, 4)]
    poses = []
    for centre in centres:
        for _ in range(60):
            turn = rotation_about_axis(rng.normal(size=3) / np.sqrt(3), np.radians(rng.uniform(0, 12)))
            poses.append(centre @ make_transform(turn, rng.normal(scale=0.003, size=3)))
    poses = np.array(poses)
    count = len(poses)
    refined = _refined(poses, rng)
    config = HypothesisConfig()
    grouped = group_hypotheses(refined, symmetry, config)
    members, support = _grouped_by_definition(refined, symmetry, config)
    assert 10 < len(members) < count  # the clusters split into several hypotheses, and absorb many poses
    np.testing.assert_array_equal(grouped.member, members)
    np.testing.assert_array_equal(grouped.support, support)
    assert grouped.support.sum() == count


def _poses_on_the_limit(config: HypothesisConfig, rng: np.random.Generator) -> np.ndarray:
    """Poses one distinct rotation apart along lines through six random poses, a few millimetres apart."""
    poses = []
    for centre in random_rotations(rng, 6):
        twists = np.zeros((15, 6))
        axis = rng.normal(size=3)
        twists[:, :3] = np.outer(np.arange(-7, 8) * config.distinct_rotation_rad, axis / np.linalg.norm(axis))
        poses.extend(make_transform(centre, rng.normal(scale=0.003, size=3)) @ se3_exp(twists))
    return np.array(poses)


@pytest.mark.parametrize("path", PATHS)
@pytest.mark.parametrize("symmetry", [*SYMMETRIES, Symmetry(spherical=True)], ids=[*IDS, "spherical"])
def test_grouping_on_the_limit_matches_its_definition(symmetry, path, rng, monkeypatch):
    """Founders and supports where every rotation lies on the limit within rounding (the compiled grouping hands
    those to the angle itself, as `_close_pairs` does), each translation a few millimetres."""
    _take_path(path, monkeypatch)
    config = HypothesisConfig()
    refined = _refined(_poses_on_the_limit(config, rng), rng)
    grouped = group_hypotheses(refined, symmetry, config)
    members, support = _grouped_by_definition(refined, symmetry, config)
    assert 3 < len(members) < len(refined.T_world_object)
    np.testing.assert_array_equal(grouped.member, members)
    np.testing.assert_array_equal(grouped.support, support)


@pytest.mark.parametrize("symmetry", SYMMETRIES, ids=IDS)
@pytest.mark.parametrize("product_size", [2_000_000, 1000], ids=["whole", "in parts"])
def test_close_pairs_on_the_limit(symmetry, product_size, rng, monkeypatch):
    monkeypatch.setattr(hypotheses, "GROUPING_PRODUCT_SIZE", product_size)
    # Poses one distinct rotation apart along lines, as the family step places them: every pair on the limit within
    # rounding, where the angle's own rounding decides (the cosines alone decide 32 of 4500 such pairs otherwise).
    config = HypothesisConfig()
    poses = _poses_on_the_limit(config, rng)
    expected = np.array(
        [
            (translation <= config.distinct_translation_m) & (rotation <= config.distinct_rotation_rad)
            for translation, rotation in (pose_distances(poses, pose, symmetry) for pose in poses)
        ]
    )
    np.fill_diagonal(expected, True)
    np.testing.assert_array_equal(_close_pairs(poses, symmetry, config), expected)


@pytest.mark.parametrize("symmetry", SYMMETRIES, ids=IDS)
def test_family_mean_weights_the_first_hypothesis_family(symmetry, rng):
    # The most likely pose, a neighbour 1.5 units away (within `mean_reach`, given in a symmetric equivalent) and
    # a likelier pose 3 units away (beyond it): the mean is that of the first two, weighted by their tempered
    # likelihoods, rotations by their chordal mean (turned about an axis across the symmetry axis z).
    config = HypothesisConfig()
    centre = make_transform(random_rotations(rng, 1)[0], rng.normal(scale=0.01, size=3))
    axis = np.array([np.cos(0.3), np.sin(0.3), 0.0])
    phi = 1.5 * config.distinct_rotation_rad
    slide = np.array([0.0, 0.0, 0.006])
    neighbour = centre @ make_transform(rotation_about_axis(axis, phi), slide)
    equivalent = symmetry.rotations[-1]
    if symmetry.axis_object is not None:
        equivalent = equivalent @ rotation_about_axis(symmetry.axis_object, 0.7)
    far = centre @ make_transform(rotation_about_axis(axis, 3.0 * config.distinct_rotation_rad), np.zeros(3))
    poses = np.array([neighbour @ make_transform(equivalent, np.zeros(3)), far, centre])
    cost = np.array([2.0, 0.5, 0.0])  # log-likelihoods -1, -0.25, 0
    refined = Refined(
        poses, np.zeros((3, 2, 6)), np.zeros((3, 2)), np.ones((3, 2)), np.zeros((3, 2)), cost, np.zeros((3, 6))
    )
    grouped = group_hypotheses(refined, symmetry, config)
    assert grouped.member[0] == 2
    mean = family_mean(refined, grouped, symmetry, config)
    w = np.exp(-1.0 / config.mean_temperature)
    expected = centre @ make_transform(
        rotation_about_axis(axis, np.arctan2(w * np.sin(phi), 1.0 + w * np.cos(phi))), np.zeros(3)
    )
    expected[:3, 3] = (centre[:3, 3] + w * neighbour[:3, 3]) / (1.0 + w)
    assert np.linalg.norm(mean[:3, 3] - expected[:3, 3]) < TOL["pose_exact_m"]
    assert rotation_angle_rad(mean, expected) < TOL["pose_exact_rad"]
