"""The pose stage end to end: pair files written by an independent program -> `yoto pose` -> pose results."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import TOL

from yoto.cli import main
from yoto.contacts import ContactEstimate, ContactPair, TactileContact, read_contact_pair, write_contact_pair
from yoto.geometry import (
    invert_transform,
    make_transform,
    random_rotations,
    rotation_about_axis,
    rotation_between,
    transform_points,
)
from yoto.localize.base import OracleLocalizer
from yoto.metrics import pose_errors
from yoto.pose.pipeline import PAPER, PoseConfig, estimate_pose


def foreign_tactile_cloud(
    surface_object: np.ndarray, n_object: np.ndarray, p_object: np.ndarray, roll: float, depth_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """A tactile cloud as another program might write it: the surface points a flat gel pressed `depth_m` into
    the object at p would touch, in a sensor frame with z into the object and an arbitrary roll.
    Returns (points_sensor, T_object_sensor)."""
    z_axis = np.array([0.0, 0.0, 1.0])
    rotation = rotation_between(z_axis, -n_object) @ rotation_about_axis(z_axis, roll)
    T_object_sensor = make_transform(rotation, p_object - depth_m * n_object)
    points = transform_points(invert_transform(T_object_sensor), surface_object)
    keep = (points[:, 2] <= 0) & (np.abs(points[:, 0]) < 0.0101) & (np.abs(points[:, 1]) < 0.0076)
    keep &= np.linalg.norm(points[:, :2], axis=1) < 0.012
    return points[keep], T_object_sensor


def write_foreign_pairs(model, folder, rng, count):
    surface = model.mesh_object.sample(400_000)
    T_mesh_object = model.T_mesh_object
    written = []
    while len(written) < count:
        i, j = rng.choice(len(model.points_object), size=2, replace=False)
        p_left, p_right = model.points_object[i].astype(float), model.points_object[j].astype(float)
        n_left, n_right = model.aggregated_normal(p_left), model.aggregated_normal(p_right)
        if np.linalg.norm(p_left - p_right) < 0.03 or n_left @ n_right > 0.5:
            continue
        T_world_object = make_transform(random_rotations(rng, 1)[0], rng.uniform([0.3, -0.2, 0.0], [0.7, 0.2, 0.3]))
        contacts, truth = {}, {}
        for side, p, n in (("left", p_left, n_left), ("right", p_right, n_right)):
            points, T_object_sensor = foreign_tactile_cloud(surface, n, p, rng.uniform(0, 2 * np.pi), 0.001)
            if len(points) < 200 or points[:, 2].min() < -1.2 * 0.001:  # something else pokes into the gel
                break
            contacts[side] = TactileContact(points, T_world_object @ T_object_sensor)
            # SPEC: the true contact is the surface point nearest the patch centroid.
            centroid_object = transform_points(T_object_sensor, points.mean(axis=0))
            nearest = surface[np.argmin(np.linalg.norm(surface - centroid_object, axis=1))]
            truth[side] = transform_points(T_mesh_object, nearest)
        if len(contacts) < 2:
            continue
        pair = ContactPair(
            model.name, contacts["left"], contacts["right"], T_world_object @ invert_transform(T_mesh_object), truth
        )
        written.append(write_contact_pair(folder / f"pair_{len(written):04d}.json", pair))
    return written


def test_oracle_recovers_poses_from_foreign_pair_files(builtin_models, tmp_path, rng, capsys):
    model = builtin_models["figurine"]
    model_path = model.save(tmp_path / "figurine.npz")
    paths = write_foreign_pairs(model, tmp_path / "pairs", rng, 6)

    assert main(["pose", str(tmp_path / "pairs"), "--oracle", "--model", str(model_path)]) == 0
    output = capsys.readouterr().out
    assert "6 poses vs ground truth (oracle)" in output
    errors_deg = []
    for path in paths:
        result = json.loads(path.with_name(path.stem + ".pose.json").read_text())
        pair = read_contact_pair(path)
        errors = pose_errors(np.array(result["T_world_object"]), pair.T_world_mesh_true, model)
        # The oracle's floor: the built-in meshes' facets (1 mm marching cubes) alone tilt normals by ~1 degree.
        assert errors["translation_mm"] < 1.5 and errors["rotation_deg"] < 3.0
        assert result["error"]["translation_mm"] == pytest.approx(errors["translation_mm"])
        # Result contact locations are in the mesh frame: the oracle returns the truth.
        assert np.allclose(result["left"]["p_object"], pair.p_mesh_true["left"], atol=TOL["float32_unit"])
        errors_deg.append(errors["rotation_deg"])
        assert set(result) >= {"T_world_object", "left", "right", "confidence", "conditioning", "latency_ms"}
        assert 0.0 <= result["confidence"] <= 1.0
    assert np.median(errors_deg) < 1.0


def test_pose_reports_bad_pairs_and_carries_on(builtin_models, tmp_path, rng, capsys):
    model = builtin_models["fruit"]
    model_path = model.save(tmp_path / "fruit.npz")
    write_foreign_pairs(model, tmp_path, rng, 1)
    (tmp_path / "zz_bad.json").write_text('{"object": "fruit"}')
    assert main(["pose", str(tmp_path), "--oracle", "--model", str(model_path)]) == 1
    output = capsys.readouterr().out
    assert "zz_bad.json: missing key 'left'" in output and "1 pair(s) failed" in output
    assert (tmp_path / "pair_0000.pose.json").exists() and not (tmp_path / "zz_bad.pose.json").exists()


class _TwoCandidates:
    """A localizer whose top candidate is wrong but whose second agrees with the pair's geometry."""

    name, needs_ground_truth = "two", True

    def __init__(self, decoys: list[np.ndarray]):
        self.decoys = decoys

    def localize(self, points_sensor, model, truth_p_object=None):
        truth = OracleLocalizer().localize(points_sensor, model, truth_p_object)[0]
        decoy = self.decoys.pop()
        wrong = ContactEstimate(decoy, model.aggregated_normal(decoy), probability=0.6)
        truth.probability = 0.4
        return [wrong, truth]


def test_joint_selection_prefers_the_geometrically_consistent_pair(builtin_models, tmp_path, rng):
    model = builtin_models["tool"]
    pair = read_contact_pair(write_foreign_pairs(model, tmp_path, rng, 1)[0])
    decoys = [model.points_object[i].astype(float) for i in (0, 5000, 10000, 15000)]
    joint = estimate_pose(pair, model, _TwoCandidates(decoys[:2]), PoseConfig(verify=False, refine=False))
    independent = estimate_pose(pair, model, _TwoCandidates(decoys[2:]), PAPER)
    for side in ("left", "right"):
        truth = transform_points(model.T_object_mesh, pair.p_mesh_true[side])
        assert np.allclose(joint.contacts[side].p_object, truth)
        assert not np.allclose(independent.contacts[side].p_object, truth)
    assert pose_errors(joint.T_world_mesh, pair.T_world_mesh_true, model)["translation_mm"] < 3.0
    assert pose_errors(independent.T_world_mesh, pair.T_world_mesh_true, model)["translation_mm"] > 10.0
    assert joint.consistency > 0.9 > independent.consistency


def test_surface_verification_and_refinement(builtin_models, tmp_path, rng):
    """Under the true pose both tactile clouds lie on the surface; a pose 2 mm / 2 deg off does not, and
    refinement brings it back to a fraction of that. Two small patches leave a slide along the surface
    weakly constrained on some pairs, so the tight bounds are on the median, the loose ones on every pair."""
    from yoto.geometry import random_perturbation, rotation_angle_rad
    from yoto.pose.refine import RefineConfig, contact_samples, refine_pose, surface_fit

    model = builtin_models["figurine"]
    config = RefineConfig()
    translation_mm, rotation_deg = [], []
    for path in write_foreign_pairs(model, tmp_path, rng, 6):
        pair = read_contact_pair(path)
        T_true = pair.T_world_mesh_true @ model.T_mesh_object
        points = np.vstack(
            [
                contact_samples(
                    pair.contact(s).points_sensor, pair.contact(s).T_world_sensor, model.point_spacing_m, config
                )
                for s in ("left", "right")
            ]
        )
        true_fit = surface_fit(model, T_true, points, config)
        assert true_fit.rms_m < 0.15e-3 and true_fit.inlier_fraction > 0.9
        perturbation = random_perturbation(rng, 0.002 / np.sqrt(3), np.radians(2.0))
        T_start = T_true @ perturbation
        assert surface_fit(model, T_start, points, config).rms_m > 2 * true_fit.rms_m
        T_refined, fit = refine_pose(model, T_start, points, config)
        assert fit.rms_m < 0.2e-3
        translation_mm.append(1e3 * np.linalg.norm(T_refined[:3, 3] - T_true[:3, 3]))
        rotation_deg.append(np.degrees(rotation_angle_rad(T_refined, T_true)))
    assert max(translation_mm) < 1.2 and max(rotation_deg) < 1.8
    assert np.median(translation_mm) < 0.3 and np.median(rotation_deg) < 0.7


def test_refinement_does_not_slide_on_a_sphere(rng):
    """A sphere constrains no rotation: refinement fixes the translation but keeps the starting rotation."""
    import trimesh

    from yoto.geometry import rotation_angle_rad
    from yoto.objects.model import ObjectModelConfig, build_object_model
    from yoto.pose.refine import RefineConfig, refine_pose

    model = build_object_model(
        trimesh.creation.icosphere(subdivisions=5, radius=0.04), "ball", ObjectModelConfig(num_points=40_000)
    )
    patch = model.points_object[np.linalg.norm(model.points_object - [0, 0, 0.04], axis=1) < 0.008].astype(float)
    patch2 = model.points_object[np.linalg.norm(model.points_object - [0.04, 0, 0], axis=1) < 0.008].astype(float)
    T_true = make_transform(random_rotations(rng, 1)[0], [0.5, 0.1, 0.2])
    points_world = transform_points(T_true, np.vstack([patch, patch2]))
    offset = make_transform(rotation_about_axis(np.array([0.3, 0.2, 0.9]), np.radians(3.0)), [0.001, -0.0005, 0.0008])
    T_start = T_true @ offset
    T_refined, fit = refine_pose(model, T_start, points_world, RefineConfig())
    assert np.linalg.norm(T_refined[:3, 3] - T_true[:3, 3]) < 0.2e-3  # the centre is pinned down
    assert abs(np.degrees(rotation_angle_rad(T_refined, T_start))) < 0.5  # the free rotation is left alone
