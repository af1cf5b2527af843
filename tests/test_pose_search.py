"""The pose stage's building blocks: the surface distance field, the batched solver, the joint two-contact
search, hypotheses, confidence and next_touch."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from conftest import TOL

from yoto.contacts import TactileContact, WorldContact, contact_in_world
from yoto.errors import InputError
from yoto.geometry import (
    invert_transform,
    make_transform,
    procrustes_rotation,
    random_rotations,
    rotate_vectors,
    rotation_about_axis,
    rotation_between,
    se3_exp,
    transform_points,
)
from yoto.objects.model import ObjectModelConfig, build_object_model
from yoto.objects.symmetry import Symmetry
from yoto.pose.confidence import FEATURES, fit_logistic, load_confidence_model, read_confidence_model
from yoto.pose.field import FieldConfig, build_surface_field, surface_field
from yoto.pose.hypotheses import Hypotheses, HypothesisConfig, group_hypotheses, is_ambiguous, pose_distances, spread
from yoto.pose.refine import Refined
from yoto.pose.search import SearchConfig, contact_shape, search_poses
from yoto.pose.solver import direction_angles, procrustes_rotations, solve_poses
from yoto.sensor.spec import GELSIGHT_MINI

SMALL = ObjectModelConfig(num_points=30_000)


@pytest.fixture(scope="module")
def box():
    return build_object_model(trimesh.creation.box(extents=(0.12, 0.08, 0.05)), "box", SMALL)


@pytest.fixture(scope="module")
def ball():
    return build_object_model(trimesh.creation.icosphere(subdivisions=5, radius=0.04), "ball", SMALL)


def test_distance_field_of_a_ball(ball, rng):
    field = build_surface_field(ball, FieldConfig(cell_m=0.001))
    directions = rng.normal(size=(2000, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    offsets = rng.uniform(-0.003, 0.003, size=2000)
    centre = transform_points(ball.T_object_mesh, np.zeros(3))  # the object frame's origin is the cloud's centroid
    points = centre + directions * (0.04 + offsets)[:, None]
    distance, normal = field.distance(points)
    # The icosphere's facets sit up to ~0.03 mm inside the sphere; the trilinear field adds a few micrometres.
    assert np.abs(distance - offsets).max() < 6e-5
    assert np.einsum("ij,ij->i", normal, directions).min() > 0.995
    far, far_normal = field.distance(np.array([[1.0, 0.0, 0.0]]))
    assert far[0] == field.band_m and np.allclose(far_normal, 0.0)


def test_key_is_invariant_and_batched_solver_agrees(rng):
    """The pair key does not change under a rigid motion; the batched Procrustes equals the single one."""
    p = rng.normal(size=(50, 3)) * 0.05
    n = rng.normal(size=(50, 3))
    offset, n_left, n_right = p[1:] - p[:-1], n[:-1], n[1:]
    R = random_rotations(rng, 1)[0]
    assert np.allclose(
        direction_angles(offset, n_left, n_right),
        direction_angles(offset @ R.T, n_left @ R.T, n_right @ R.T),
        atol=TOL["arccos_rad"],
    )
    H = rng.normal(size=(40, 3, 3))
    batched = procrustes_rotations(H)
    for k in range(40):
        single, _ = procrustes_rotation(H[k], np.eye(3))
        assert np.allclose(batched[k], single, atol=TOL["float"])


def _press(model, p_object, n_object, T_world_object, depth=0.001, radius=0.008, whole_pad=False):
    """A tactile contact of a flat gel pressed at p along -n (points of the parent cloud under the gel, within
    `radius` of its centre, or on the whole GelSight Mini pad)."""
    rotation = rotation_between(np.array([0.0, 0.0, 1.0]), -n_object)
    T_object_sensor = make_transform(rotation, p_object - depth * n_object)
    points = transform_points(invert_transform(T_object_sensor), model.points_object.astype(float))
    if whole_pad:
        under = np.all(np.abs(points[:, :2]) < np.array(GELSIGHT_MINI.pad_size_m) / 2, axis=1)
    else:
        under = np.linalg.norm(points[:, :2], axis=1) < radius
    keep = (points[:, 2] <= 0) & under
    return TactileContact(points[keep], T_world_object @ T_object_sensor), T_object_sensor


def test_search_finds_the_truth_where_the_candidates_are_wrong(box, rng):
    """Two contacts on two faces of a box: the localizers' (wrong) candidates do not fit, the search's matches
    cover the true pose and the whole slide the two faces leave free."""
    T_world_object = make_transform(random_rotations(rng, 1)[0], [0.5, 0.0, 0.2])
    contacts = {}
    for side, p, n in (("left", [0.02, 0.01, 0.025], [0, 0, 1.0]), ("right", [0.06, -0.01, 0.0], [1.0, 0, 0])):
        contacts[side], _ = _press(box, np.array(p), np.array(n), T_world_object)
    world = {side: contact_in_world(contact) for side, contact in contacts.items()}
    shapes = {
        side: contact_shape(
            contacts[side].points_sensor, world[side].p_sensor, world[side].n_sensor, SearchConfig().samples
        )
        for side in contacts
    }
    assert np.abs(shapes["left"].curvatures).max() < 5.0  # a flat patch
    from yoto.contacts import ContactEstimate

    wrong = {
        side: [ContactEstimate(np.array([-0.06, 0.0, 0.0]), np.array([-1.0, 0, 0]), probability=0.9)] for side in world
    }
    matches = search_poses(box, world, shapes, wrong)
    T = matches.T_world_object
    translation = np.linalg.norm(T[:, :3, 3] - T_world_object[:3, 3], axis=1)
    cos_angle = (np.einsum("kij,ij->k", T[:, :3, :3], T_world_object[:3, :3]) - 1) / 2
    near = (translation < 0.004) & (cos_angle > np.cos(np.radians(4.0)))
    assert near.any()
    # The free slide (along the edge the two faces share, y) shows up as many translations along it.
    along = (T[near, :3, 3] - T_world_object[:3, 3]) @ T_world_object[:3, 1]
    slide = (T[:, :3, 3] - T_world_object[:3, 3]) @ T_world_object[:3, 1]
    aligned = cos_angle > np.cos(np.radians(4.0))
    assert np.ptp(slide[aligned]) > 0.02 and np.abs(along).min() < 0.004


def _refined(poses: np.ndarray, rms: np.ndarray) -> Refined:
    count = len(poses)
    return Refined(
        poses,
        np.zeros((count, 2, 6)),
        rms,
        np.ones((count, 2)),
        np.zeros((count, 2)),
        np.zeros(count),
        np.zeros((count, 6)),
    )


def test_hypotheses_are_grouped_modulo_symmetry(box, rng):
    symmetry = box.symmetry
    T = make_transform(random_rotations(rng, 1)[0], [0.5, 0.0, 0.2])
    flipped = T @ make_transform(symmetry.rotations[1], np.zeros(3))
    turned = T @ make_transform(rotation_about_axis(np.array([0, 0, 1.0]), np.radians(20)), np.zeros(3))
    poses = np.array([T, flipped, turned])
    grouped = group_hypotheses(_refined(poses, np.full((3, 2), 3e-5)), symmetry, HypothesisConfig())
    assert len(grouped) == 2  # the flip is the same pose of a box; the 20 deg turn is not
    assert grouped.probability.sum() == pytest.approx(1.0)
    assert is_ambiguous(grouped, HypothesisConfig())  # equal fits share the probability
    worse = group_hypotheses(
        _refined(poses, np.array([[3e-5] * 2, [3e-5] * 2, [2e-4] * 2])), symmetry, HypothesisConfig()
    )
    assert worse.probability[0] > 0.999 and not is_ambiguous(worse, HypothesisConfig())
    # Probabilities are the likelihoods tempered: the two groups' odds are exp(log-likelihood gap / temperature).
    config = HypothesisConfig(temperature=4.0)
    tempered = group_hypotheses(_refined(poses, np.array([[3e-5] * 2, [3e-5] * 2, [4e-5] * 2])), symmetry, config)
    gap = tempered.log_likelihood[0] - tempered.log_likelihood[1]
    assert gap > 1.0 and tempered.probability[0] / tempered.probability[1] == pytest.approx(np.exp(gap / 4.0))


def test_spread_weighs_each_hypothesis_by_its_distance_from_the_first_modulo_symmetry(rng):
    T = make_transform(random_rotations(rng, 1)[0], [0.5, 0.0, 0.2])
    turned = T @ make_transform(rotation_about_axis(np.array([0, 0, 1.0]), np.radians(10.0)), np.zeros(3))
    slid = T @ make_transform(np.eye(3), [0.003, 0.0, 0.0])
    far = T @ make_transform(np.eye(3), [0.1, 0.0, 0.0])
    poses = np.array([T, turned, slid, far])
    hypotheses = Hypotheses(poses, np.array([0.4, 0.3, 0.2, 0.1]), np.zeros(4), np.arange(4), np.ones(4, np.int64))
    scale_m, scale_rad = 0.005, np.radians(5.0)
    # 10 deg is 2 units, 3 mm 0.6, 100 mm is capped at 4: 0.3 * 2 + 0.2 * 0.6 + 0.1 * 4.
    assert spread(hypotheses, Symmetry(), scale_m, scale_rad, 4.0) == pytest.approx(1.12, abs=1e-9)
    # About a continuous symmetry axis (z) the turn is the same pose: it no longer counts.
    about_z = Symmetry(axis_object=np.array([0.0, 0.0, 1.0]))
    assert spread(hypotheses, about_z, scale_m, scale_rad, 4.0) == pytest.approx(0.52, abs=1e-9)
    one = Hypotheses(poses[:1], np.ones(1), np.zeros(1), np.zeros(1, np.int64), np.ones(1, np.int64))
    assert spread(one, Symmetry(), scale_m, scale_rad, 4.0) == 0.0


def test_neighbour_poses_turn_and_slide_each_pose_about_its_own_axes(rng):
    from yoto.pose.hypotheses import neighbour_poses

    config = HypothesisConfig()
    poses = np.array([make_transform(R, [0.5, 0.0, 0.2]) for R in random_rotations(rng, 2)])
    near = neighbour_poses(poses, config)
    assert near.shape == (24, 4, 4)
    for h in range(2):
        translation, rotation = pose_distances(near[12 * h : 12 * (h + 1)], poses[h], Symmetry())
        turned = rotation > 1e-4
        assert turned.sum() == 6 and np.allclose(rotation[turned], config.neighbour_rotation_rad)
        assert np.allclose(translation[turned], 0.0) and np.allclose(translation[~turned], 0.006)
        # Slid along the pose's own object axes: in the object frame, each step is along one axis.
        steps = np.einsum("ij,kj->ki", poses[h, :3, :3].T, near[12 * h : 12 * (h + 1), :3, 3] - poses[h, :3, 3])
        assert np.allclose(np.sort(np.abs(steps[~turned]), axis=1)[:, :2], 0.0, atol=1e-12)


def test_logistic_confidence_fit_and_files(tmp_path, rng):
    x = rng.normal(size=(4000, len(FEATURES)))
    true_weights = np.zeros(len(FEATURES))
    true_weights[:3] = [2.0, -1.0, 0.5]
    y = rng.random(4000) < 1.0 / (1.0 + np.exp(-(0.3 + x @ true_weights)))
    model = fit_logistic(x, y, l2=1e-4)
    assert np.allclose(model.weights[:3] * (1.0 / model.scale[:3]), true_weights[:3], atol=0.2)
    path = model.save(tmp_path / "confidence.json")
    again = read_confidence_model(path)
    assert np.allclose(again.predict_many(x[:10]), model.predict_many(x[:10]), atol=TOL["float"])
    shipped = load_confidence_model(None)  # the parameters shipped with YOTO
    assert shipped.features == FEATURES and 0.0 < shipped.predict(dict(zip(FEATURES, x[0]))) < 1.0
    (tmp_path / "bad.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(InputError, match="refit it"):
        read_confidence_model(tmp_path / "bad.json")


def test_next_touch_separates_two_slid_hypotheses(box, rng):
    """Two hypotheses 15 mm apart along the box's long axis: the suggested touch is where they disagree (an end
    face or an edge), reachable, and None is returned when only one hypothesis remains."""
    from yoto.pose.hypotheses import Hypotheses
    from yoto.pose.next_touch import suggest_next_touch

    T = make_transform(random_rotations(rng, 1)[0], [0.5, 0.0, 0.2])
    slid = T @ make_transform(np.eye(3), [0.015, 0.0, 0.0])
    contacts = {}
    for side, p, n in (("left", [0.0, 0.0, 0.025], [0, 0, 1.0]), ("right", [0.0, 0.0, -0.025], [0, 0, -1.0])):
        contacts[side], _ = _press(box, np.array(p), np.array(n), T)
    from yoto.contacts import ContactPair

    pair = ContactPair("box", contacts["left"], contacts["right"])
    two = Hypotheses(np.array([T, slid]), np.array([0.5, 0.5]), np.zeros(2), np.arange(2), np.ones(2, dtype=np.int64))
    touch = suggest_next_touch(box, two, pair)
    assert touch is not None and touch.disagreement_m > 0.001
    assert abs(touch.p_object[0]) > 0.045  # near an end of the 120 mm long axis, where the slide shows
    assert np.linalg.norm(box.nearest_surface_point(touch.p_object) - touch.p_object) < 1e-3
    one = Hypotheses(T[None], np.ones(1), np.zeros(1), np.zeros(1, np.int64), np.ones(1, np.int64))
    assert suggest_next_touch(box, one, pair) is None
    assert touch.to_json(box)["sensor"] in ("left", "right")
    assert np.allclose(
        touch.to_json(box)["n_object"], rotate_vectors(box.T_mesh_object, touch.n_object), atol=TOL["float"]
    )


def test_press_clearance_follows_the_approach_however_far_it_starts(box):
    """A sensor moves along its z until its gel touches, presses, and its housing must clear the object: a press
    tilted 30 deg on the box's top face puts the housing into the box whether it starts touching or 20 mm back
    (beyond the distance field's band); a square press clears and makes a contact; one that meets nothing is
    clear but makes no contact."""
    from yoto.pose.next_touch import NextTouchConfig, presses_clear, sensor_pose_at

    field, config = surface_field(box), NextTouchConfig()
    top = sensor_pose_at(np.array([0.0, 0.0, 0.025]), np.array([0.0, 0.0, 1.0]))
    back = make_transform(np.eye(3), [0.0, 0.0, -0.02])
    tilted = top @ make_transform(rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.radians(30.0)), np.zeros(3))
    poses = np.array([top, top @ back, tilted, tilted @ back])
    assert presses_clear(field, poses, config).tolist() == [True, True, False, False]
    assert presses_clear(field, poses, config, contact=True).tolist() == [True, True, False, False]
    up = make_transform(np.eye(3), [0.0, 0.0, 0.1])  # above the box, facing away from it
    assert presses_clear(field, up[None], config).tolist() == [True]
    assert presses_clear(field, up[None], config, contact=True).tolist() == [False]
    corner = sensor_pose_at(np.array([0.06, 0.04, 0.025]), np.array([1.0, 1.0, 1.0]) / np.sqrt(3.0))
    assert presses_clear(field, corner[None], config, contact=True).tolist() == [False]  # a tip, not a patch


def test_solve_poses_recovers_exact_poses(rng):
    T = make_transform(random_rotations(rng, 1)[0], [0.4, 0.1, 0.3])
    p = rng.normal(size=(2, 3)) * 0.05
    n = rng.normal(size=(2, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    worlds = [
        WorldContact(np.zeros(3), np.zeros(3), transform_points(T, p[i]), rotate_vectors(T, n[i])) for i in (0, 1)
    ]
    batch = solve_poses(p[:1], n[:1], p[1:], n[1:], worlds[0], worlds[1])
    assert np.allclose(batch.T_world_object[0], T, atol=TOL["pose_exact_m"])
    assert batch.separation_error_m[0] < TOL["pose_exact_m"]


def _box_with_a_third_touch(box, rng, slides_m):
    """Two contacts on opposite faces of the box (free to slide), an estimate whose hypotheses are the true pose
    slid along x by each of `slides_m`, and a third touch on an end face by the left sensor."""
    from yoto.contacts import ContactEstimate, ContactPair
    from yoto.pose.hypotheses import Hypotheses
    from yoto.pose.pipeline import PoseEstimate
    from yoto.pose.solver import solve_pose

    T = make_transform(random_rotations(rng, 1)[0], [0.5, 0.0, 0.2])
    hypotheses = np.array([T @ make_transform(np.eye(3), [slide, 0.0, 0.0]) for slide in slides_m])
    contacts, truth = {}, {}
    for side, p, n in (("left", [0.01, 0.0, 0.025], [0, 0, 1.0]), ("right", [-0.01, 0.01, -0.025], [0, 0, -1.0])):
        contacts[side], _ = _press(box, np.array(p), np.array(n), T, whole_pad=True)
        truth[id(contacts[side].points_sensor)] = (np.array(p), np.array(n))
    pair = ContactPair("box", contacts["left"], contacts["right"])
    touch, _ = _press(box, np.array([0.06, 0.0, 0.0]), np.array([1.0, 0, 0]), T, whole_pad=True)
    truth[id(touch.points_sensor)] = (np.array([0.06, 0.0, 0.0]), np.array([1.0, 0, 0]))
    world = {side: contact_in_world(contacts[side]) for side in contacts}
    located = {side: ContactEstimate(np.zeros(3), np.array([0, 0, 1.0])) for side in contacts}
    located["right"] = ContactEstimate(np.array([0.0, 0.0, -0.025]), np.array([0, 0, -1.0]))
    count = len(slides_m)
    estimate = PoseEstimate(
        object_name="box",
        method="test",
        T_world_object=hypotheses[0],
        T_world_mesh=hypotheses[0] @ box.T_object_mesh,
        contacts=located,
        candidates={side: [located[side]] for side in contacts},
        world=world,
        solution=solve_pose(located["left"], located["right"], world["left"], world["right"]),
        hypotheses=Hypotheses(
            hypotheses, np.full(count, 1.0 / count), np.zeros(count), np.arange(count), np.ones(count, np.int64)
        ),
        ambiguous=True,
        confidence=0.5,
    )
    return pair, touch, estimate, T, truth


class _KnownLocations:
    """A test localizer that knows where each of the test's clouds was pressed."""

    name = "known"
    needs_ground_truth = False

    def __init__(self, truth):
        self.truth = truth

    def localize(self, points_sensor, model, truth_p_object=None):
        from yoto.contacts import ContactEstimate

        p, n = self.truth[id(points_sensor)]
        return [ContactEstimate(p, n)]


def test_fusing_the_next_touch_picks_the_true_hypothesis(box, rng):
    """Two contacts on opposite faces leave the box free to slide; a third touch on an end face, by the left
    sensor, tells the true pose from a slid one (the estimate's hypotheses are refined with all three clouds)."""
    from yoto.pose.pipeline import PoseConfig, fuse_next_touch

    pair, touch, estimate, T, _ = _box_with_a_third_touch(box, rng, [0.012, 0.0])
    fused = fuse_next_touch(pair, box, estimate, touch, "left", PoseConfig())
    assert np.linalg.norm(fused.T_world_object[:3, 3] - T[:3, 3]) < 0.002
    assert not fused.ambiguous and fused.hypotheses.probability[0] > 0.99


def test_fusing_the_next_touch_finds_a_truth_the_first_pair_missed(box, rng):
    """When no hypothesis of the first pair is right (both slid along x, which the top and bottom faces leave
    free), the new touch on the end face and the contact that stayed are localized as a pair of their own, and the
    seeds of its search are verified with all three clouds. Three faces of a box still leave the slide along y
    free, so only x, z and the rotation are checked."""
    from yoto.pose.pipeline import PoseConfig, fuse_next_touch

    pair, touch, estimate, T, truth = _box_with_a_third_touch(box, rng, [0.03, -0.03])

    def offset(fused):
        """Per hypothesis: translation off the truth along x and z (object frame), rotation off it modulo the
        box's symmetry."""
        relative = invert_transform(T) @ fused.hypotheses.T_world_object
        _, rotation = pose_distances(fused.hypotheses.T_world_object, T, box.symmetry)
        return np.abs(relative[:, [0, 2], 3]).max(axis=1), rotation

    alone = fuse_next_touch(pair, box, estimate, touch, "left", PoseConfig())
    assert offset(alone)[0].min() > 0.02  # refining the slid poses cannot get there
    fused = fuse_next_touch(pair, box, estimate, touch, "left", PoseConfig(), localizer=_KnownLocations(truth))
    translation, rotation = offset(fused)
    # Among the hypotheses, as refining a right hypothesis gives (the box turned a quarter about z, the touch on a
    # side face, explains the three contacts as well: the first hypothesis may be either).
    assert np.any((translation < 0.002) & (rotation < np.radians(1.0)))


def test_pose_cli_fuses_a_retouch_read_from_files(box, rng, tmp_path, capsys):
    """`yoto pose PAIR.json --retouch TOUCH.json --sensor left`: the pair's contacts on the box's top and bottom
    leave it free to slide; the end-face touch read from its file fixes x, z and the rotation in the fused result
    (NAME.retouch.pose.json, with its error against the pair's ground truth); a touch file that names no sensor
    needs --sensor."""
    from yoto.cli import main
    from yoto.contacts import write_contact_pair
    from yoto.io import write_json_atomic, write_ply_points

    pair, touch, _, T, _ = _box_with_a_third_touch(box, rng, [0.0])
    pair.T_world_mesh_true = T @ box.T_object_mesh
    pair_path = write_contact_pair(tmp_path / "pair_0000.json", pair)
    write_ply_points(tmp_path / "touch_left.ply", touch.points_sensor)
    touch_path = write_json_atomic(
        tmp_path / "touch.json", {"points": "touch_left.ply", "T_world_sensor": touch.T_world_sensor}
    )
    model_path = box.save(tmp_path / "box.npz")
    command = ["pose", str(pair_path), "--retouch", str(touch_path), "--model", str(model_path), "--search", "always"]
    assert main(command) == 1
    assert "names no 'sensor'" in capsys.readouterr().out
    odd = write_json_atomic(
        tmp_path / "odd.json", {"points": "touch_left.ply", "T_world_sensor": np.eye(4), "sensor": "up"}
    )
    assert main(["pose", str(pair_path), "--retouch", str(odd), "--model", str(model_path)]) == 1
    assert "'sensor' must be 'left' or 'right'" in capsys.readouterr().out
    assert main([*command, "--sensor", "left", "--out", str(tmp_path / "out")]) == 0
    assert "with the left sensor's touch" in capsys.readouterr().out
    result = json.loads((tmp_path / "out" / "pair_0000.retouch.pose.json").read_text())
    assert result["retouch"]["sensor"] == "left" and "error" in result
    # Among the result's hypotheses (y stays free); the box turned a quarter about z, the touch on a side face,
    # explains the three contacts as well (a log-likelihood 0.1-0.9 apart), so the first may be either.
    T_fused = np.array([h["T_world_object"] for h in result["hypotheses"]]) @ box.T_mesh_object
    relative = invert_transform(T) @ T_fused
    _, rotation = pose_distances(T_fused, T, box.symmetry)
    assert np.any((np.abs(relative[:, [0, 2], 3]).max(axis=1) < 0.002) & (rotation < np.radians(1.0)))
    assert np.allclose(result["hypotheses"][0]["T_world_object"], result["T_world_object"])


def test_a_sequence_of_touches_resolves_what_one_leaves_free(box, rng):
    """Top and bottom contacts leave the box free to slide in x and y: the first touch (left sensor, end face)
    fixes x but leaves the y-slid hypothesis; the second (right sensor, side face), fused with the first as an
    earlier touch, fixes y too."""
    from yoto.pose.hypotheses import Hypotheses
    from yoto.pose.pipeline import PoseConfig, fuse_next_touch

    pair, touch, estimate, T, _ = _box_with_a_third_touch(box, rng, [0.0])
    slides = [(0.0, 0.0), (0.012, 0.0), (0.0, 0.01), (0.012, 0.01)]
    poses = np.array([T @ make_transform(np.eye(3), [dx, dy, 0.0]) for dx, dy in slides])
    estimate.hypotheses = Hypotheses(poses, np.full(4, 0.25), np.zeros(4), np.arange(4), np.ones(4, np.int64))
    config = PoseConfig(suggest_next_touch=False)
    first = fuse_next_touch(pair, box, estimate, touch, "left", config)
    slid = invert_transform(T) @ first.hypotheses.T_world_object
    assert first.ambiguous and np.abs(slid[:, 0, 3]).max() < 0.002  # x fixed, y not
    assert np.abs(slid[:, 1, 3]).max() > 0.004  # a hypothesis slid along y remains (where along the free y the
    # refinements leave it, 5-10 mm, moves with the field's interpolation: 0.5 mm cells 5.0 mm, 1 mm cells over 8)
    side, _ = _press(box, np.array([0.0, 0.04, 0.0]), np.array([0.0, 1.0, 0.0]), T, whole_pad=True)
    second = fuse_next_touch(pair, box, first, side, "right", config, earlier=((touch, "left"),))
    relative = invert_transform(T) @ second.T_world_object
    assert np.abs(relative[:3, 3]).max() < 0.002 and not second.ambiguous


def test_best_distinct_hypotheses_from_the_most_likely_poses_as_from_all(rng):
    """The pose stage groups only the most likely poses when they hold enough distinct hypotheses: the founders it
    picks are those of grouping every pose (clusters of near-duplicates, tied scores, too few distinct ones)."""
    from yoto.objects.symmetry import Symmetry
    from yoto.pose.pipeline import _best_distinct

    centres = [make_transform(R, rng.normal(size=3) * 0.02) for R in random_rotations(rng, 60)]
    poses = np.array([centres[i] @ make_transform(np.eye(3), rng.normal(size=3) * 0.001) for i in range(60)] * 5)
    rms = np.round(rng.uniform(2e-5, 2e-4, size=(len(poses), 2)), 5)  # rounded: many exact ties
    refined = _refined(poses[rng.permutation(len(poses))], rms)
    config = HypothesisConfig()
    for count in (5, 40, 70):
        expected = group_hypotheses(refined, Symmetry(), config).member[:count]
        assert np.array_equal(_best_distinct(refined, Symmetry(), config, count), expected)
    assert len(_best_distinct(refined, Symmetry(), config, 70)) == 60  # fewer distinct than asked: all of them


def test_family_poses_follow_what_two_contacts_leave_free(rng):
    """Two contacts on opposite sides of a cylinder's body leave it free to turn about its axis and slide along it:
    the two weakest directions of the clouds' information are (nearly) that turn and that slide, and the poses along
    them keep both clouds on the surface, where two units along the strongest directions move them off it."""
    from yoto.pose.hypotheses import family_poses, weak_directions
    from yoto.pose.refine import RefineConfig, contact_points

    can = build_object_model(trimesh.creation.cylinder(radius=0.03, height=0.1, sections=128), "can", SMALL)
    axis = rotate_vectors(can.T_object_mesh, np.array([0.0, 0.0, 1.0]))  # the mesh's z in the canonical frame
    field = surface_field(can)
    T = make_transform(random_rotations(rng, 1)[0], [0.5, 0.0, 0.2])
    side_a = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    side_a /= np.linalg.norm(side_a)
    contacts = []
    for sensor, n in enumerate((side_a, -side_a)):
        contact, _ = _press(can, 0.03 * n + 0.01 * axis, n, T)
        contacts.append(contact_points(contact.points_sensor, contact.T_world_sensor, sensor, 0.001, RefineConfig()))
    config = HypothesisConfig(family_of=1, family_directions=2)
    capture_m = RefineConfig().max_distance_m
    directions = weak_directions(field, contacts, T[None], config, capture_m)[0]
    unit = np.array([config.distinct_rotation_rad] * 3 + [config.distinct_translation_m] * 3)
    for weak in directions[:2] / unit:  # in units: rotation about the axis, translation along it, or a mix
        across = np.concatenate([weak[:3] - (weak[:3] @ axis) * axis, weak[3:] - (weak[3:] @ axis) * axis])
        assert np.linalg.norm(across) < 0.15 * np.linalg.norm(weak)
    one = Hypotheses(T[None], np.ones(1), np.zeros(1), np.zeros(1, np.int64), np.ones(1, np.int64))
    family = family_poses(field, contacts, one, config, capture_m)
    assert family.shape == (2 * 2 * 36, 4, 4)

    def off_surface(poses):
        worst = np.zeros(len(poses))
        for contact in contacts:
            q = np.einsum(
                "kij,pj->kpi", (np.linalg.inv(poses) @ contact.T_world_sensor)[:, :3, :3], contact.points_sensor
            )
            q += (np.linalg.inv(poses) @ contact.T_world_sensor)[:, None, :3, 3]
            worst = np.maximum(worst, np.abs(field.distance(q, with_gradient=False)[0]).max(axis=1))
        return worst

    near = family.reshape(2, 72, 4, 4)[:, 32:40].reshape(-1, 4, 4)  # up to 4 units (20 deg, 20 mm) both ways
    assert off_surface(near).max() < 3e-4  # the can's facets and the field's interpolation, not the pose
    strong = T @ se3_exp(directions[-2:] * 2.0)  # two units along the two strongest directions
    assert off_surface(strong).min() > 2e-3


def test_thin_crossings_are_strips_across_the_pad():
    """A contact crossing the pad as a strip narrower than the limit is a thin crossing; a wide band across the
    pad, a blob inside it, a blob at one edge and no contact are not."""
    from yoto.pose.next_touch import NextTouchConfig, _gel_points, _thin_crossing

    config = NextTouchConfig()
    gel = _gel_points(config.contact_spacing_m)
    x, y = gel[:, 0], gel[:, 1]
    masks = [
        np.abs(x) < 0.0008,  # 1.6 mm strip across the pad
        np.abs(x - y) < 0.001,  # a diagonal strip
        np.abs(x) < 0.004,  # an 8 mm band across it
        np.hypot(x, y) < 0.003,  # a blob inside
        np.hypot(x - x.max(), y) < 0.004,  # a blob at one edge
        np.zeros(len(gel), dtype=bool),
    ]
    assert _thin_crossing(np.stack(masks), gel, config).tolist() == [True, True, False, False, False, False]


def test_refinement_starts_its_corrections_where_asked(box, rng):
    """With no iteration, the refinement returns its starting corrections and their cost under the prior: the
    corrections an earlier refinement found are where a fused refinement starts (fuse_next_touch)."""
    from yoto.pose.refine import CalibrationPrior, RefineConfig, contact_points, refine_hypotheses

    T = make_transform(random_rotations(rng, 1)[0], [0.5, 0.0, 0.2])
    contact, _ = _press(box, np.array([0.0, 0.0, 0.025]), np.array([0.0, 0.0, 1.0]), T)
    contacts = [contact_points(contact.points_sensor, contact.T_world_sensor, 0, 0.001, RefineConfig())]
    start = rng.normal(scale=[0.01] * 3 + [0.001] * 3, size=(2, 2, 6))
    prior, field = CalibrationPrior(), surface_field(box)
    refined = refine_hypotheses(field, contacts, np.stack([T, T]), prior, RefineConfig(iterations=0), start)
    assert np.allclose(refined.corrections, start, atol=1e-12)
    assert np.allclose(refined.correction_cost, np.einsum("ksi,i,ksi->k", start, prior.information(), start))
    assert np.allclose(refine_hypotheses(field, contacts, T[None], prior, RefineConfig(iterations=0)).corrections, 0)
