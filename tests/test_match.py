"""The training-free matched-filter localizer: simulated GelSight contacts found on the object, their sensor
poses, ambiguity on featureless surfaces, and clear errors."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TOL

pytest.importorskip("open3d")

from yoto.errors import DegenerateGeometryError  # noqa: E402
from yoto.geometry import rotation_angle_rad  # noqa: E402
from yoto.localize import make_localizer  # noqa: E402
from yoto.localize.match import MapGrid, MatchConfig, MatchLocalizer, plane_costs  # noqa: E402
from yoto.localize.match.rings import ContactRings, RingDescriptors, RingGrid, ring_distances  # noqa: E402
from yoto.localize.scaled_match import ScaledMatchLocalizer  # noqa: E402
from yoto.simulate.scenarios import PairSimulator  # noqa: E402
from yoto.tactile_image import tactile_height_image, tactile_spacing_at_most, tactile_spacing_m  # noqa: E402


def test_finds_contacts_on_a_distinctive_surface(fruit_contacts):
    """The fruit's bumps make a contact's height map unique: the best candidate is the true place, and its
    sensor pose (a by-product of the match) is the true one."""
    model, contacts = fruit_contacts
    localizer = make_localizer("match")
    # The matched filter, with finer cells only for contacts too small for its default maps.
    assert isinstance(localizer, ScaledMatchLocalizer) and not localizer.needs_ground_truth
    assert isinstance(localizer.default, MatchLocalizer)
    hits = 0
    for points_sensor, p_true, T_object_sensor_true in contacts:
        candidates = localizer.localize(points_sensor, model)
        assert 1 <= len(candidates) <= localizer.config.belief.num_candidates
        probabilities = np.array([c.probability for c in candidates])
        assert ((probabilities >= 0) & (probabilities <= 1)).all() and probabilities.sum() <= 1.0 + 1e-9
        assert np.all(np.diff([c.score for c in candidates]) <= TOL["float_round_trip"])  # best first
        best = candidates[0]
        if np.linalg.norm(best.p_object - p_true) < 2.5e-3:
            hits += 1
            T_object_sensor = np.array(best.details["match_T_object_sensor"])
            # The press axis is well determined; the roll about it only as well as the contact's shape allows.
            press_axis_cos = T_object_sensor[:3, 2] @ T_object_sensor_true[:3, 2]
            assert np.degrees(np.arccos(min(press_axis_cos, 1.0))) < 3.0
            assert np.degrees(rotation_angle_rad(T_object_sensor, T_object_sensor_true)) < 15.0
            assert best.details["match_residual_mm"] < 0.1
    assert hits >= 5


def test_every_rotation_of_the_sensor_is_searched(builtin_models, fruit_contacts):
    """Rolling the tactile cloud about the sensor axis leaves the answer in place. (Without the free-space
    term: these contacts cover the whole pad, and a rolled copy would claim the pad's corners saw nothing.)"""
    from yoto.geometry import rotation_about_axis

    model, contacts = fruit_contacts
    localizer = MatchLocalizer(MatchConfig(free_space=False))
    for points_sensor, p_true, _ in contacts[:3]:
        found = localizer.localize(points_sensor, model)[0].p_object
        assert np.linalg.norm(found - p_true) < 2.5e-3
        for angle in (0.7, 2.9):
            rolled = points_sensor @ rotation_about_axis(np.array([0.0, 0.0, 1.0]), angle).T
            assert np.linalg.norm(localizer.localize(rolled, model)[0].p_object - found) < 1.0e-3


@pytest.fixture(scope="module")
def box():
    """A plain box: flat faces everywhere."""
    import trimesh

    from yoto.objects.model import ObjectModelConfig, build_object_model

    return build_object_model(trimesh.creation.box((0.12, 0.08, 0.05)), "box", ObjectModelConfig(num_points=40_000))


def test_a_flat_face_is_ambiguous_not_wrong(box):
    """Pressing a flat region matches many places; every candidate still lies on the surface, facing the sensor."""
    x, y = np.meshgrid(np.arange(-4e-3, 4e-3, 1e-4), np.arange(-4e-3, 4e-3, 1e-4))
    depth = 0.3e-3
    points_sensor = np.stack([x.ravel(), y.ravel(), np.full(x.size, -depth)], axis=1)
    candidates = MatchLocalizer().localize(points_sensor, box)
    assert len(candidates) >= 3
    spread = np.ptp(np.array([c.p_object for c in candidates]), axis=0).max()
    assert spread > 0.01  # distinct places, none singled out
    for candidate in candidates:
        distance = abs(box.raycaster.signed_distance(candidate.p_object))
        assert distance < 0.5e-3


def test_plane_costs_remove_offset_and_tilt():
    """The matched filter's cost is zero for a height map equal to the anchor's up to a plane, and the plane
    it reports is that plane."""
    grid = MapGrid(0.0015, 0.0105)
    x, y = grid.centres.T
    rng = np.random.default_rng(3)
    anchor = rng.normal(0.0, 3e-4, grid.size).astype(np.float32)
    beta_true = np.array([2e-4, 0.05, -0.03])
    contact = anchor + beta_true[0] + beta_true[1] * x + beta_true[2] * y
    mask = np.ones((1, grid.size), dtype=np.float32)
    valid = np.ones((grid.size, 1), dtype=np.float32)
    heights = anchor[:, None]
    cost, beta = plane_costs(
        mask, contact[None].astype(np.float32), valid, heights, heights * heights, grid.centres, True, 5e-4
    )
    assert cost[0, 0] < TOL["float_round_trip"]
    np.testing.assert_allclose(beta[:, 0, 0], beta_true, rtol=1e-2, atol=1e-6)
    # Offset only: the tilt is left as error.
    cost_offset, _ = plane_costs(
        mask, contact[None].astype(np.float32), valid, heights, heights * heights, grid.centres, False, 5e-4
    )
    assert cost_offset[0, 0] > 1e-8


def bumpy_heights(xy: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random smooth height field at (N, 2) positions: a quadratic plus a few 3 mm bumps (metres)."""
    a, b, c = rng.normal(0.0, 20.0, 3)
    heights = 0.5 * a * xy[:, 0] ** 2 + b * xy[:, 0] * xy[:, 1] + 0.5 * c * xy[:, 1] ** 2
    for centre, height in zip(rng.uniform(-0.008, 0.008, (4, 2)), rng.normal(0.0, 3e-4, 4), strict=True):
        heights += height * np.exp(-np.sum((xy - centre) ** 2, axis=1) / (2 * 0.003**2))
    return heights


def rings_of(grid: RingGrid, heights: np.ndarray, used: np.ndarray) -> ContactRings:
    means, magnitudes = grid.describe(heights)
    return ContactRings(used, np.where(used, means, 0.0), np.where(used[:, None], magnitudes, 0.0))


def test_ring_distance_ignores_roll_and_plane_and_bounds_the_fine_cost(rng):
    """The coarse stage's distance is zero for the anchor's own surface seen rolled and tilted, and never exceeds
    the squared height difference after the best roll (on the ring samples) and plane: pruning by it is safe."""
    grid = RingGrid(0.00075, 0.0105, 24, 6)
    xy = grid.centres
    surfaces = [bumpy_heights(xy, rng) for _ in range(6)]
    descriptors = RingDescriptors.from_samples(grid, np.array(surfaces))
    used = np.zeros(len(grid.radii), dtype=bool)
    used[[0, 1, 2, 4, 6, 7]] = True  # the rings a contact covers (not necessarily the inner ones)
    weights = np.repeat(np.where(used, grid.radii, 0.0) / grid.radii[used].sum(), grid.angles) / grid.angles
    for steps in (0, 5, 13):  # rolls by multiples of the angular step
        roll = 2.0 * np.pi * steps / grid.angles
        rolled = np.stack(
            [np.cos(roll) * xy[:, 0] - np.sin(roll) * xy[:, 1], np.sin(roll) * xy[:, 0] + np.cos(roll) * xy[:, 1]], 1
        )
        contact = bumpy_heights(rolled, np.random.default_rng(rng.integers(1 << 30)))
        seen = surfaces[2]  # the anchor's surface under the sensor, rolled: sample at the rolled positions
        seen = np.roll(seen.reshape(-1, grid.angles), -steps, axis=1).ravel() + 2e-4 + 0.03 * xy[:, 0] - 0.02 * xy[:, 1]
        distance = ring_distances(descriptors, rings_of(grid, seen, used))
        assert distance[2] < 1e-12 < distance[[0, 1, 3, 4, 5]].min()
        # Lower bound: brute force over every roll of the samples and the least-squares offset and tilt.
        distance = ring_distances(descriptors, rings_of(grid, contact, used))
        design = np.stack([np.ones(len(xy)), xy[:, 0], xy[:, 1]], axis=1) * np.sqrt(weights)[:, None]
        for anchor, surface in enumerate(surfaces):
            costs = []
            for shift in range(grid.angles):
                difference = contact - np.roll(surface.reshape(-1, grid.angles), shift, axis=1).ravel()
                target = difference * np.sqrt(weights)
                _, residual, *_ = np.linalg.lstsq(design, target, rcond=None)
                costs.append(float(residual[0]))
            assert distance[anchor] <= min(costs) * (1 + 1e-5) + 1e-12


def test_a_thin_strip_uses_the_fallback_coarse_stage(box):
    """A contact too narrow to cover its rings (a strip 2 mm wide, as on an edge) still localizes: the coarse
    stage falls back to an offset-only filter of every anchor. On the box's flat face it is ambiguous, not lost."""
    from yoto.localize.match.contact import contact_image
    from yoto.localize.match.rings import contact_rings

    x, y = np.meshgrid(np.arange(-5e-3, 5e-3, 1e-4), np.arange(-1e-3, 1e-3, 1e-4))
    points_sensor = np.stack([x.ravel(), y.ravel(), np.full(x.size, -0.3e-3)], axis=1)
    localizer = MatchLocalizer()
    anchors = localizer.prepare_object(box)
    image = contact_image(points_sensor, anchors.grid.radius_m, localizer.config)
    assert contact_rings(image, anchors.rings.grid, localizer.config.ring_coverage).used.sum() < 2
    candidates = localizer.localize(points_sensor, box)
    assert len(candidates) >= 3
    for candidate in candidates:
        assert abs(box.raycaster.signed_distance(candidate.p_object)) < 0.5e-3


def test_anchor_maps_are_built_once(builtin_models):
    model = builtin_models["figurine"]
    localizer = MatchLocalizer()
    first = localizer.prepare_object(model)
    assert localizer.prepare_object(model) is first
    assert first.heights.shape == (len(first.points_object), first.grid.size)
    rings = first.rings.grid
    assert first.rings.terms.shape == (len(rings.radii), len(first.points_object), 2 * rings.harmonics)
    # Anchors on the surface at about the configured spacing, each with most of its disc on the surface.
    assert np.abs(np.linalg.norm(first.normals_object, axis=1) - 1.0).max() < TOL["float32_unit"]
    assert np.median(first.valid.mean(axis=1)) > 0.8
    assert (
        0.5 * model.meta["surface_area_m2"] / 0.002**2
        < len(first.points_object)
        < 1.5 * model.meta["surface_area_m2"] / 0.002**2
    )


def test_a_contact_too_small_for_the_default_cells_is_matched_with_finer_ones(builtin_models):
    """A contact of about one default height-map cell (a cap 1 mm across) is too small for the default maps (a
    clear error from them, not a guess), and `make_localizer("match")` matches it with finer cells instead."""
    xy = np.random.default_rng(0).uniform(-0.5e-3, 0.5e-3, (400, 2))
    cap = np.column_stack([xy, -0.1e-3 + 200.0 * (xy**2).sum(axis=1)])  # a 5 mm radius cap pressed 0.1 mm
    with pytest.raises(DegenerateGeometryError, match="too small to match"):
        MatchLocalizer().localize(cap, builtin_models["fruit"])
    candidates = make_localizer("match").localize(cap, builtin_models["fruit"])
    assert candidates and all(c.details["match_cell_mm"] < 1.5 for c in candidates)


def test_pose_command_defaults_to_the_matched_filter(builtin_models, tmp_path, rng, capsys):
    """`yoto pose` with no method on pair files another program wrote (plain surface samples, not this project's
    simulator): most poses of the bumpy fruit come out right, without any training."""
    import json

    from test_pose import write_foreign_pairs

    from yoto.cli import main

    model = builtin_models["fruit"]
    model_path = model.save(tmp_path / "fruit.npz")
    paths = write_foreign_pairs(model, tmp_path / "pairs", rng, 4)
    assert main(["pose", str(tmp_path / "pairs"), "--model", str(model_path)]) == 0
    assert "(match)" in capsys.readouterr().out
    errors = [json.loads(path.with_suffix(".pose.json").read_text())["error"] for path in paths]
    good = [e["translation_mm"] < 2.0 and e["rotation_deg"] < 3.0 for e in errors]
    assert sum(good) >= 3, errors


def test_a_helper_process_localizes_a_pair_as_this_process_does(builtin_models):
    """With a helper process, a pair's right contact gets exactly the candidates and world-side measurement it gets
    here (the model sent to the helper, its anchor maps built there)."""
    from yoto.localize.helper import LocalizerProcess
    from yoto.pose.pipeline import localize_contacts

    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=0).pair
    localizer = make_localizer("match")
    alone, world_alone, _ = localize_contacts(pair, model, localizer)
    with LocalizerProcess(localizer) as helper:
        together, world, latency = localize_contacts(pair, model, localizer, helper)
    for side in ("left", "right"):
        assert len(together[side]) == len(alone[side]) > 0
        for a, b in zip(alone[side], together[side], strict=True):
            assert np.array_equal(a.p_object, b.p_object) and a.probability == b.probability
            assert a.details["match_T_object_sensor"] == b.details["match_T_object_sensor"]
        assert np.array_equal(world[side].p_world, world_alone[side].p_world)
        assert np.array_equal(world[side].n_world, world_alone[side].n_world)
    assert latency["localize_pair"] >= latency["localize_left"] > 0 and latency["localize_right"] > 0


def test_pose_command_on_both_cores_writes_the_same_poses(builtin_models, tmp_path, rng, monkeypatch):
    """`yoto pose --both-cores` (each pair's right contact in a helper process) writes the poses, hypotheses and
    contacts that one process writes."""
    import json

    from test_pose import write_foreign_pairs

    from yoto.cli import main
    from yoto.localize.helper import LocalizerProcess

    sent = []
    submit = LocalizerProcess.submit
    monkeypatch.setattr(LocalizerProcess, "submit", lambda self, *a, **k: sent.append(1) or submit(self, *a, **k))

    model = builtin_models["fruit"]
    model_path = model.save(tmp_path / "fruit.npz")
    paths = write_foreign_pairs(model, tmp_path / "pairs", rng, 2)
    for out, extra in (("one", []), ("both", ["--both-cores"])):
        command = ["pose", str(tmp_path / "pairs"), "--model", str(model_path), "--out", str(tmp_path / out)]
        assert main(command + extra) == 0
    assert len(sent) == len(paths)  # only --both-cores sent contacts to the helper, one per pair
    for path in paths:
        one, both = (
            json.loads((tmp_path / out / path.with_suffix(".pose.json").name).read_text()) for out in ("one", "both")
        )
        assert both["T_world_object"] == one["T_world_object"]
        assert both["hypotheses"] == one["hypotheses"] and both["confidence"] == one["confidence"]
        assert both["right"]["p_object"] == one["right"]["p_object"]


def test_the_dense_cloud_check_agrees_with_the_measured_spacing(rng):
    """The height image tells a dense cloud from a sparse one without a k-d tree (`tactile_spacing_at_most`):
    whenever it says the spacing is at most a bound, the measured spacing is; and it says so for dense clouds."""
    for spacing in (4e-5, 6.3e-5, 1e-4, 1.3e-4, 2e-4, 4e-4):
        side = np.arange(-0.006, 0.006, spacing)
        grid = np.stack(np.meshgrid(side, side, indexing="ij"), axis=-1).reshape(-1, 2)
        for jitter in (0.0, 0.3):
            xy = grid + rng.uniform(-jitter, jitter, grid.shape) * spacing
            local = np.column_stack([xy, 1e-4 * rng.standard_normal(len(xy))])
            measured = tactile_spacing_m(local)
            for bound in (1e-4, 0.0002 / 1.5, 3e-4):
                if tactile_spacing_at_most(local, bound):
                    assert measured <= bound
            if spacing <= 6.3e-5:  # a GelSight Mini's cloud: no k-d tree needed at the default 0.2 mm pixel
                assert tactile_spacing_at_most(local, 0.0002 / 1.5)
            if measured > 0.0002 / 1.5:
                assert not tactile_spacing_at_most(local, 0.0002 / 1.5)


def test_mask_only_sampling_matches_sampling(fruit_contacts):
    _, contacts = fruit_contacts
    image = tactile_height_image(contacts[0][0], 0.0105, 0.0002, 1)
    x, y = np.meshgrid(np.linspace(-0.012, 0.012, 41), np.linspace(-0.012, 0.012, 37), indexing="ij")
    for mask in (image.mask, ~image.filled):
        _, expected = image.sample(x, y, mask)
        np.testing.assert_array_equal(image.covered(x, y, mask), expected)


def test_the_helper_keeps_the_models_the_caller_records_and_raises_what_it_raised(builtin_models):
    """The caller sends a model only when the helper does not hold it, and both forget the oldest beyond
    `models_kept` in the same order: every answer is computed on its own model (the oracle's normal is the model's
    own), and an error in the helper is raised by the caller."""
    from yoto.contacts import TactileContact
    from yoto.localize.helper import LocalizerProcess

    oracle = make_localizer("oracle")
    contact = TactileContact(np.zeros((40, 3)), np.eye(4))  # the oracle reads only the truth
    held = []
    with LocalizerProcess(oracle, models_kept=2) as helper:
        for name in ("fruit", "tool", "fruit", "figurine", "fruit", "tool"):
            model = builtin_models[name]
            truth = model.points_object[100].astype(np.float64)
            candidates, _, _ = helper.submit(contact, model, truth).result()
            assert np.array_equal(
                candidates[0].n_object, oracle.localize(contact.points_sensor, model, truth)[0].n_object
            )
            held.append([key == model.fingerprint for key in helper._sent])
        with pytest.raises(ValueError, match="ground-truth"):
            helper.submit(contact, builtin_models["fruit"]).result()
    # first in, first out: fruit; fruit, tool; (fruit held); tool, figurine; figurine, fruit; fruit, tool
    assert [row.index(True) for row in held] == [0, 1, 0, 1, 1, 1]
    assert [len(row) for row in held] == [1, 2, 2, 2, 2, 2]


def test_the_candidate_icp_goes_on_with_the_starts_that_fit_best(fruit_contacts):
    """`keep_best`: after one iteration only the best-fitting starts iterate further (each exactly as it would
    have alone); the others keep their one-step pose. Near starts fit better than far ones on the bumpy fruit."""
    from dataclasses import replace

    from yoto.geometry import make_transform
    from yoto.registration import point_to_plane_gauss_newton

    model, contacts = fruit_contacts
    points_sensor, _, T_object_sensor_true = contacts[0]
    samples = points_sensor[:: max(1, len(points_sensor) // 200)]
    shifts_m = [2e-4, 5e-3, 4e-4, 6e-3, 6e-4, 4e-3]  # along the sensor's x: near, far, near, ...
    starts = np.stack([T_object_sensor_true @ make_transform(np.eye(3), [s, 0.0, 0.0]) for s in shifts_m])
    config = MatchConfig().icp
    full = point_to_plane_gauss_newton(model, samples, starts, config)
    one_step = point_to_plane_gauss_newton(model, samples, starts, replace(config, iterations=1))
    pruned = point_to_plane_gauss_newton(model, samples, starts, config, keep_best=3)
    near, far = [0, 2, 4], [1, 3, 5]
    assert np.abs(full[far] - one_step[far]).max() > 1e-5  # the later iterations move the far starts
    assert np.abs(pruned[near] - full[near]).max() < TOL["float"]
    assert np.abs(pruned[far] - one_step[far]).max() < TOL["float"]


def test_the_candidate_icp_lookups_answer_as_the_models_kd_tree(fruit_contacts, monkeypatch):
    """The candidate ICP's parent surface (pykdtree where installed) finds the same nearest points as the model's
    cKDTree, near the surface and beyond the reach, and the localizer's candidates are bitwise the same with either."""
    pytest.importorskip("pykdtree")
    import yoto.localize.match.localizer as match_localizer
    from yoto.localize.match.lookup import ParentSurface, one_openmp_thread, parent_surface

    model, contacts = fruit_contacts
    surface = parent_surface(model)
    assert parent_surface(model) is surface and surface.kdtree is not model.kdtree  # cached, and pykdtree's
    rng = np.random.default_rng(3)
    # Points up to 3 mm off the surface along the normal, some beyond the 2 mm reach: found or not, as the cKDTree.
    index = rng.choice(len(model.points_object), 2000, replace=False)
    offsets = rng.uniform(-0.003, 0.003, (2000, 1)) * model.normals_object[index] + rng.normal(0, 2e-4, (2000, 3))
    points = model.points_object[index].astype(np.float64) + offsets
    with one_openmp_thread():
        gaps, found_index = surface.kdtree.query(points, distance_upper_bound=0.002)
    expected_gaps, expected_index = model.kdtree.query(points, distance_upper_bound=0.002)
    found = np.isfinite(expected_gaps)
    assert 0 < found.sum() < len(points)
    assert np.array_equal(np.isfinite(gaps), found) and np.array_equal(found_index[found], expected_index[found])
    assert np.allclose(gaps[found], expected_gaps[found], rtol=0, atol=TOL["float_round_trip"])

    localizer = MatchLocalizer()
    points_sensor = contacts[0][0]
    fast = localizer.localize(points_sensor, model)
    monkeypatch.setattr(
        match_localizer, "parent_surface", lambda m: ParentSurface(m.points_object, m.normals_object, m.kdtree)
    )
    slow = localizer.localize(points_sensor, model)
    assert len(fast) == len(slow)
    for a, b in zip(fast, slow, strict=True):
        assert np.array_equal(a.p_object, b.p_object) and a.probability == b.probability and a.details == b.details


def test_the_contact_centre_measures_only_the_patch_around_the_point_nearest_the_centroid(rng):
    """contact_in_sensor measures distances from the point nearest the centroid only for the points that can lie
    within the fit radius of it: the same answer, bit for bit, as measuring every point, on a dome, on a ring whose
    nearest point lies far from its centroid, and on a cloud too sparse for the radius (the nearest points then)."""
    from yoto.contacts import LOCAL_FIT_MIN_POINTS, LOCAL_FIT_RADIUS_M, _contact_in_sensor
    from yoto.pointcloud import covariance_eigh

    def every_point(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        centroid = np.array([points[:, axis].mean() for axis in range(3)])
        offsets = points - centroid
        from_centroid = np.einsum("ij,ij->i", offsets, offsets)
        from_nearest = points - points[np.argmin(from_centroid)]
        squared = np.einsum("ij,ij->i", from_nearest, from_nearest)
        neighbours = np.flatnonzero(squared <= LOCAL_FIT_RADIUS_M**2)
        if len(neighbours) < LOCAL_FIT_MIN_POINTS:
            neighbours = np.argsort(squared)[:LOCAL_FIT_MIN_POINTS]
        normal = covariance_eigh(points[neighbours])[2][:, 0]
        normal = normal if normal[2] <= 0 else -normal
        along = offsets @ normal
        closest = np.argpartition(from_centroid - along * along, 8)[:8]
        return centroid + along[closest].mean() * normal, normal

    xy = rng.uniform(-0.008, 0.008, (20000, 2))
    dome = np.column_stack([xy, -0.001 + 10.0 * (xy**2).sum(axis=1)])
    radius = np.hypot(xy[:, 0], xy[:, 1])
    ring = dome[(radius > 0.004) & (radius < 0.007)]
    sparse = dome[:60]
    for points in (dome, ring, sparse):
        centre, normal = _contact_in_sensor(points)
        expected_centre, expected_normal = every_point(points)
        assert np.array_equal(centre, expected_centre) and np.array_equal(normal, expected_normal)
