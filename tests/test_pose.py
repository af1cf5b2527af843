"""The pose stage end to end: pair files written by an independent program -> `yoto pose` -> pose results."""

from __future__ import annotations

import json
from dataclasses import replace

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
    se3_exp,
    transform_points,
)
from yoto.metrics import pose_errors
from yoto.pose.pipeline import PAPER, PoseConfig, _pair_clouds, estimate_pose


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
    surface = model.mesh_object.sample(400_000, seed=rng)
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

    assert main(["pose", str(tmp_path / "pairs"), "--oracle", "--model", str(model_path), "--search", "never"]) == 0
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
        # Result contact locations are in the mesh frame: where the measured contact lies under the pose, which for
        # the oracle's pose is the true contact up to the pose's own error.
        assert np.linalg.norm(np.subtract(result["left"]["p_object"], pair.p_mesh_true["left"])) < 1.5e-3
        errors_deg.append(errors["rotation_deg"])
        assert set(result) >= {"T_world_object", "left", "right", "confidence", "conditioning", "latency_ms"}
        assert set(result) >= {"hypotheses", "ambiguous", "next_touch"}
        assert 0.0 <= result["confidence"] <= 1.0
        assert np.allclose(result["hypotheses"][0]["T_world_object"], result["T_world_object"])
    assert np.median(errors_deg) < 1.5  # the pose stage allows each sensor 1 mm / 1 deg of calibration error


def test_pose_reports_bad_pairs_and_carries_on(builtin_models, tmp_path, rng, capsys):
    model = builtin_models["fruit"]
    model_path = model.save(tmp_path / "fruit.npz")
    write_foreign_pairs(model, tmp_path, rng, 1)
    (tmp_path / "zz_bad.json").write_text('{"object": "fruit"}')
    assert main(["pose", str(tmp_path), "--oracle", "--model", str(model_path)]) == 1
    output = capsys.readouterr().out
    assert "zz_bad.json: missing key 'left'" in output and "1 pair(s) failed" in output
    assert (tmp_path / "pair_0000.pose.json").exists() and not (tmp_path / "zz_bad.pose.json").exists()


class _Decoys:
    """A localizer that puts each contact somewhere wrong (one candidate, far from the truth)."""

    name, needs_ground_truth = "decoys", False

    def __init__(self, decoys: list[np.ndarray]):
        self.decoys = decoys

    def localize(self, points_sensor, model, truth_p_object=None):
        decoy = self.decoys.pop()
        return [ContactEstimate(decoy, model.aggregated_normal(decoy), probability=0.9)]


def test_joint_search_recovers_what_the_localizers_missed(builtin_models, tmp_path, rng):
    """Both localizer candidates are wrong: the paper's stage solves the wrong pair; the joint two-contact search
    finds the surface locations whose geometry fits the pair and verifies them with the clouds. Of four pairs one
    (the first) leaves a family of poses that explain both contacts equally well (40 hypotheses of equal
    probability, the first 70-100 deg off whatever the seeds' score): the search must get the other three, as the
    first hypothesis or as one tied with it (within one log unit: on the third pair a pose 28 mm / 174 deg off
    explains both contacts 0.2 units better than the truth, and whether the stage reaches it moves with any score
    change)."""
    from yoto.pose.hypotheses import pose_distances

    model = builtin_models["figurine"]
    decoys = [model.points_object[i].astype(float) for i in (0, 20000, 5000, 30000)]
    right = 0
    for path in write_foreign_pairs(model, tmp_path, rng, 4):
        pair = read_contact_pair(path)
        found = estimate_pose(pair, model, _Decoys(decoys[:2]), PoseConfig(search="always", suggest_next_touch=False))
        paper = estimate_pose(pair, model, _Decoys(decoys[2:]), PAPER)
        assert found.searched
        hypotheses = found.hypotheses
        translation, rotation = pose_distances(
            hypotheses.T_world_object, pair.T_world_mesh_true @ model.T_mesh_object, model.symmetry
        )
        tied = hypotheses.log_likelihood >= hypotheses.log_likelihood[0] - 1.0
        right += bool(np.any(tied & (translation < 0.002) & (rotation < np.radians(3.0))))
        assert pose_errors(paper.T_world_mesh, pair.T_world_mesh_true, model)["translation_mm"] > 10.0
        # The first hypothesis is the pose; probabilities are a distribution over the hypotheses found.
        assert np.allclose(found.hypotheses.T_world_object[0], found.T_world_object)
        assert found.hypotheses.probability.sum() <= 1.0 + TOL["float"]
        assert np.all(np.diff(found.hypotheses.probability) <= 0)
    assert right >= 3


def _miscalibrated(pair, rng, translation_m=0.001, rotation_rad=np.radians(1.0)):
    """The pair with each reported sensor pose off by a rigid error of about the given size (reported = true @ E)."""
    from yoto.geometry import random_perturbation

    errors = {side: random_perturbation(rng, translation_m / np.sqrt(3), rotation_rad) for side in ("left", "right")}
    for side in ("left", "right"):
        contact = pair.contact(side)
        contact.T_world_sensor = contact.T_world_sensor @ errors[side]
    return errors


def test_refinement_with_sensor_corrections(builtin_models, tmp_path, rng):
    """Under 1 mm / 1 deg calibration error the two clouds cannot both lie on the surface under one rigid pose:
    refining the pose with a correction per sensor fits both again and lands closer to the truth than a rigid
    fit of both clouds (a calibration prior of almost zero)."""
    from yoto.geometry import random_perturbation, rotation_angle_rad
    from yoto.pose.field import surface_field
    from yoto.pose.refine import CalibrationPrior, RefineConfig, evaluate_fit, refine_hypotheses

    model = builtin_models["figurine"]
    field = surface_field(model)
    config = RefineConfig()
    joint, rigid, fit_true, fit_joint = [], [], [], []
    for path in write_foreign_pairs(model, tmp_path, rng, 6):
        pair = read_contact_pair(path)
        _miscalibrated(pair, rng)
        T_true = pair.T_world_mesh_true @ model.T_mesh_object
        contacts = _pair_clouds(pair, model, PoseConfig(refine_config=config))
        starts = np.array([T_true @ random_perturbation(rng, 0.0015, np.radians(1.5)) for _ in range(3)])
        for prior, store in ((CalibrationPrior(), joint), (CalibrationPrior(1e-6, 1e-6), rigid)):
            refined = refine_hypotheses(field, contacts, starts, prior, config)
            store += [
                np.linalg.norm(T[:3, 3] - T_true[:3, 3]) * 1e3 + np.degrees(rotation_angle_rad(T, T_true))
                for T in refined.T_world_object
            ]
            if store is joint:
                fit_joint += list(refined.fit_rms_m.max(axis=1))
        fit_true += list(evaluate_fit(field, contacts, T_true[None], None, config)[0].max(axis=1))
    assert np.median(fit_true) > 3e-4  # the reported sensor poses leave the clouds far off the true surface
    assert np.median(fit_joint) < 5e-5  # the corrections bring them back onto it
    assert np.median(joint) < 0.7 * np.median(rigid)  # and the pose is better for it (mm + deg)


def test_refinement_does_not_slide_on_a_sphere(rng):
    """A sphere constrains no rotation: refinement fixes the translation but keeps the starting rotation."""
    import trimesh

    from yoto.geometry import rotation_angle_rad
    from yoto.objects.model import ObjectModelConfig, build_object_model
    from yoto.pose.field import surface_field
    from yoto.pose.refine import CalibrationPrior, ContactPoints, RefineConfig, refine_hypotheses

    model = build_object_model(
        trimesh.creation.icosphere(subdivisions=5, radius=0.04), "ball", ObjectModelConfig(num_points=40_000)
    )
    assert model.symmetry.spherical
    T_true = make_transform(random_rotations(rng, 1)[0], [0.5, 0.1, 0.2])
    contacts = []
    for sensor, centre in enumerate(([0, 0, 0.04], [0.04, 0, 0])):
        patch = model.points_object[np.linalg.norm(model.points_object - centre, axis=1) < 0.006].astype(float)
        T_world_sensor = T_true @ make_transform(np.eye(3), centre)  # any frame will do: points are given in it
        contacts.append(ContactPoints(patch[::10] - centre, T_world_sensor, sensor, np.zeros((0, 3))))
    offset = make_transform(rotation_about_axis(np.array([0.3, 0.2, 0.9]), np.radians(3.0)), [0.001, -0.0005, 0.0008])
    T_start = T_true @ offset
    refined = refine_hypotheses(
        surface_field(model), contacts, T_start[None], CalibrationPrior(1e-6, 1e-6), RefineConfig(iterations=20)
    )
    T_refined = refined.T_world_object[0]
    assert np.linalg.norm(T_refined[:3, 3] - T_true[:3, 3]) < 0.2e-3  # the centre is pinned down
    # The free rotation is left alone (up to what the icosphere's facets pin down).
    assert abs(np.degrees(rotation_angle_rad(T_refined, T_start))) < 1.5


def test_refined_log_likelihood_tells_the_truth_from_a_wrong_pose(builtin_models, tmp_path, rng):
    """The benchmark's diagnosis of a missing truth: the true pose, refined from there, explains the contacts as
    well as the pose stage's right answer does (so a truth it scores better was never reached), and a pose 0.3 m
    away, where no cloud reaches the surface, explains them far worse."""
    from yoto.localize import OracleLocalizer
    from yoto.pose.pipeline import refined_log_likelihood

    model = builtin_models["figurine"]
    truth, away, found = [], [], []
    for path in write_foreign_pairs(model, tmp_path, rng, 3):
        pair = read_contact_pair(path)
        _miscalibrated(pair, rng)
        T_true = pair.T_world_mesh_true @ model.T_mesh_object
        truth.append(refined_log_likelihood(pair, model, T_true))
        away.append(refined_log_likelihood(pair, model, T_true @ make_transform(np.eye(3), [0.3, 0.0, 0.0])))
        estimate = estimate_pose(pair, model, OracleLocalizer(), PoseConfig(suggest_next_touch=False))
        if pose_errors(estimate.T_world_mesh, pair.T_world_mesh_true, model)["translation_mm"] < 2.0:
            found.append(truth[-1] - float(estimate.hypotheses.log_likelihood[0]))
    assert found  # the oracle's pose is right on at least one of them
    assert np.all(np.abs(found) < 5.0)  # refining from the truth lands where the pose stage did
    assert np.all(np.array(away) < np.array(truth) - 100.0)


def test_true_corrections_bring_the_reported_sensors_onto_the_true_ones(builtin_models):
    """The benchmark refines a missing truth from its true sensor corrections: under them (and the true pose) both
    clouds lie on the surface as the simulation pressed them, under none they sit off it by the calibration error."""
    from yoto.pose.field import surface_field
    from yoto.pose.pipeline import refined_log_likelihood, true_corrections
    from yoto.pose.refine import evaluate_fit
    from yoto.simulate.scenarios import PairSimulator, ScenarioConfig

    model = builtin_models["figurine"]
    scenario = ScenarioConfig(calibration_translation_m=0.001, calibration_rotation_rad=float(np.radians(1.0)))
    simulated = PairSimulator(model, scenario).pair(seed=11, index=0)
    pair, config = simulated.pair, PoseConfig(suggest_next_touch=False)
    corrections = true_corrections(pair, simulated.T_world_sensor_true)
    for side, correction in zip(("left", "right"), corrections):
        moved = pair.contact(side).T_world_sensor @ se3_exp(correction)
        assert np.allclose(moved, simulated.T_world_sensor_true[side], atol=1e-9)
    contacts = _pair_clouds(pair, model, config)
    T_true = simulated.T_world_object[None]
    field = surface_field(model, config.field_config)
    rms_true, _, _ = evaluate_fit(field, contacts, T_true, corrections[None], config.refine_config)
    rms_none, _, _ = evaluate_fit(field, contacts, T_true, np.zeros((1, 2, 6)), config.refine_config)
    assert rms_true.max() < 60e-6 < rms_none.max()
    from_truth = refined_log_likelihood(pair, model, simulated.T_world_object, config, corrections)
    assert from_truth > -15.0  # a right pose's log-likelihood (right poses mostly fit at -2 to -12)


def test_strict_seed_score_counts_clouds_that_touch_nothing_as_the_worst_fit(builtin_models, tmp_path, rng):
    """The cheap score of unrefined seeds: a seed that puts both clouds beyond the capture range, touching nothing,
    scores as badly as clouds whose every point is off by the truncation (a distance field clamped far from the
    surface reads as a cloud lying flat at an offset, which once outranked seeds near the truth that touched the
    surface imperfectly), and far below the truth."""
    from yoto.pose.field import surface_field
    from yoto.pose.refine import STRICT_SEED_SCORE, CalibrationPrior, evaluate_offsets

    model = builtin_models["figurine"]
    field = surface_field(model)
    config = STRICT_SEED_SCORE
    worst = -0.5 * 2 * (config.fit_tau_m / config.surface_noise_m) ** 2  # both contacts fully truncated
    for path in write_foreign_pairs(model, tmp_path, rng, 3):
        pair = read_contact_pair(path)
        _miscalibrated(pair, rng)
        T_true = pair.T_world_mesh_true @ model.T_mesh_object
        contacts = _pair_clouds(pair, model, PoseConfig(refine_config=config))
        seeds = np.array([T_true, T_true @ make_transform(np.eye(3), [0.3, 0.0, 0.0])])
        truth, away = evaluate_offsets(field, contacts, seeds, CalibrationPrior(), config)
        assert away <= worst
        assert truth > worst / 2


def test_strict_seed_score_sees_free_space_beside_an_edge():
    """A contact 3 mm from a box's edge, the other mid-face: sliding the box so that the first contact lies further
    from the edge keeps both clouds on the faces (the clouds alone cannot tell), but puts the object where the pad
    felt nothing; the cheap score's free-space points rank the slid seeds below the truth."""
    import trimesh

    from yoto.objects.model import ObjectModelConfig, build_object_model
    from yoto.pose.field import surface_field
    from yoto.pose.refine import STRICT_SEED_SCORE, CalibrationPrior, contact_points, evaluate_offsets

    model = build_object_model(
        trimesh.creation.box(extents=[0.08, 0.06, 0.04]), "box", ObjectModelConfig(num_points=40_000)
    )
    surface = model.mesh_object.sample(200_000, seed=np.random.default_rng(0))
    low, high = surface.min(axis=0), surface.max(axis=0)
    config = STRICT_SEED_SCORE
    contacts = []
    for sensor, (p, n) in enumerate((([high[0], high[1] - 0.003, 0.0], [1.0, 0, 0]), ([low[0], 0, 0], [-1.0, 0, 0]))):
        points, T_world_sensor = foreign_tactile_cloud(surface, np.array(n), np.array(p), 0.0, 0.001)
        contacts.append(contact_points(points, T_world_sensor, sensor, model.point_spacing_m, config))
    seeds = np.array([np.eye(4)] + [make_transform(np.eye(3), [0.0, slide, 0.0]) for slide in (0.004, 0.008)])
    field = surface_field(model)
    truth, *slid = evaluate_offsets(field, contacts, seeds, CalibrationPrior(), config)
    assert np.all(np.array(slid) < truth - 10.0)
    blind = evaluate_offsets(field, contacts, seeds, CalibrationPrior(), replace(config, verify_free_points=0))
    assert np.all(np.abs(blind[1:] - blind[0]) < 1.0)  # the clouds alone: a tie


def test_the_family_step_runs_only_when_the_search_left_the_first_hypothesis_undecided(builtin_models, monkeypatch):
    """After the search, poses along the weakest directions of the most likely hypotheses are refined (the family
    step) unless the first hypothesis already holds `decisive_probability` and fits to `decisive_log_likelihood`;
    `family_if_decisive` runs it anyway. Where it runs, it adds its poses to the hypotheses' pool."""
    from yoto.localize import make_localizer
    from yoto.pose import pipeline
    from yoto.pose.field import FieldConfig
    from yoto.simulate.scenarios import PairSimulator

    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=0).pair
    candidates, world, _ = pipeline.localize_contacts(pair, model, make_localizer("match"))
    families = []
    fill = pipeline._fill_family

    def recorded(*arguments, **settings):
        refined, hypotheses = fill(*arguments, **settings)
        families.append(len(refined.T_world_object) - len(arguments[2].T_world_object))
        return refined, hypotheses

    monkeypatch.setattr(pipeline, "_fill_family", recorded)
    base = PoseConfig(search="always", suggest_next_touch=False, field_config=FieldConfig(cell_m=0.002))
    decisive = {"decisive_probability": 0.0, "decisive_log_likelihood": -np.inf}
    runs = {
        "undecided": replace(base, decisive_probability=1.01),
        "decisive": replace(base, **decisive),
        "decisive, family anyway": replace(base, family_if_decisive=True, **decisive),
    }
    counts = {}
    for name, config in runs.items():
        families.clear()
        estimate = pipeline.pose_from_candidates(pair, model, candidates, world, config, "match")
        assert len(estimate.hypotheses) >= 1
        counts[name] = list(families)
    assert counts["decisive"] == []
    assert len(counts["undecided"]) == 1 and counts["undecided"][0] > 0
    assert counts["decisive, family anyway"] == counts["undecided"]


def test_the_rescue_verifies_the_seeds_again_only_when_nothing_explains_the_contacts(builtin_models, monkeypatch):
    """After the search (and the family step), a first hypothesis that explains the contacts worse than
    `rescue_log_likelihood` sends the search's seeds through a wider verification (`_rescue`); its poses join the
    pool, so the first hypothesis can only explain the contacts better. Above the threshold nothing changes."""
    from yoto.localize import make_localizer
    from yoto.pose import pipeline
    from yoto.pose.field import FieldConfig
    from yoto.simulate.scenarios import PairSimulator

    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=0).pair
    candidates, world, _ = pipeline.localize_contacts(pair, model, make_localizer("match"))
    pools = []
    rescue = pipeline._rescue

    def recorded(field, contacts, seeds, score, refined, symmetry, config, *arguments, **settings):
        # The seeds' cheap scores come from the first pass, not computed again: they must be the seeds' own.
        fresh = pipeline.LOCAL.offsets(field, contacts, seeds, config.calibration, config.refine_config)
        assert np.array_equal(score, fresh)
        more, hypotheses = rescue(field, contacts, seeds, score, refined, symmetry, config, *arguments, **settings)
        pools.append((len(seeds), len(refined.T_world_object), len(more.T_world_object)))
        return more, hypotheses

    monkeypatch.setattr(pipeline, "_rescue", recorded)
    screens = []  # (seeds screened, points per contact of the short refinement) of each verification
    verify = pipeline._verify_and_refine

    def verified(field, contacts, seeds, symmetry, config, screened, *arguments, **settings):
        screens.append((screened, config.refine_config.screen_points))
        return verify(field, contacts, seeds, symmetry, config, screened, *arguments, **settings)

    monkeypatch.setattr(pipeline, "_verify_and_refine", verified)
    # A narrow first pass, so that the wider one has something to add.
    base = PoseConfig(
        search="always",
        suggest_next_touch=False,
        field_config=FieldConfig(cell_m=0.002),
        screened=8,
        seeds_refined=2,
        rescue_screened=60,
        rescue_refined=12,
        rescue_screen_points=6,
    )
    estimates = {}
    for name, threshold in (("never", -np.inf), ("always", np.inf)):
        pools.clear()
        config = replace(base, rescue_log_likelihood=threshold)
        estimates[name] = (pipeline.pose_from_candidates(pair, model, candidates, world, config, "match"), list(pools))
    (never, never_pools), (always, always_pools) = estimates["never"], estimates["always"]
    assert never_pools == []
    assert len(always_pools) == 1
    seeds, before, after = always_pools[0]
    assert seeds > 60 and after >= before + 12  # every seed the search found, and at least the new full refinements
    assert always.hypotheses.log_likelihood[0] >= never.hypotheses.log_likelihood[0] - 1e-9
    # Only the rescue's own verification screens on `rescue_screen_points`; the first pass keeps refine_config's.
    assert (60, 6) in screens and (8, base.refine_config.screen_points) in screens
    assert all(points == base.refine_config.screen_points for screened, points in screens if screened != 60)


def test_auto_searches_where_the_candidates_first_hypothesis_fits_poorly(builtin_models):
    """`search="auto"` skips the joint search only where the candidates' first hypothesis is decisive and also
    explains the contacts at least as well as `search_unless_log_likelihood`: a pose the candidates alone make
    certain can still be one that fits worse than the truth (a banana's, 8 mm along it)."""
    from yoto.localize import make_localizer
    from yoto.pose import pipeline
    from yoto.pose.field import FieldConfig
    from yoto.simulate.scenarios import PairSimulator

    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=0).pair
    candidates, world, _ = pipeline.localize_contacts(pair, model, make_localizer("match"))
    decisive = PoseConfig(
        suggest_next_touch=False,
        field_config=FieldConfig(cell_m=0.002),
        decisive_probability=0.0,
        decisive_log_likelihood=-np.inf,
        decisive_featured=0,
    )
    searched = {}
    for name, threshold in (("any fit", -np.inf), ("fits well", -10.0), ("no fit is enough", np.inf)):
        config = replace(decisive, search_unless_log_likelihood=threshold)
        estimate = pipeline.pose_from_candidates(pair, model, candidates, world, config, "match")
        searched[name] = (estimate.searched, estimate.hypotheses.log_likelihood[0])
    assert searched["any fit"][0] is False and searched["no fit is enough"][0] is True
    # The candidates' first hypothesis of this pair fits better than -10: searched exactly as with no threshold.
    assert searched["any fit"][1] > -10.0 and searched["fits well"] == searched["any fit"]


def test_the_rescue_also_runs_where_the_first_hypothesis_holds_too_little_probability(builtin_models, monkeypatch):
    """However well the first hypothesis fits, the wider verification (`_rescue`) runs where it holds less than
    `rescue_probability` (the truth of an ambiguous pair can lie among the seeds the first pass did not screen), and
    not where it holds more."""
    from yoto.localize import make_localizer
    from yoto.pose import pipeline
    from yoto.pose.field import FieldConfig
    from yoto.simulate.scenarios import PairSimulator

    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=0).pair
    candidates, world, _ = pipeline.localize_contacts(pair, model, make_localizer("match"))
    probabilities = []
    rescue = pipeline._rescue

    def recorded(*arguments, **settings):
        probabilities.append(True)
        return rescue(*arguments, **settings)

    monkeypatch.setattr(pipeline, "_rescue", recorded)
    base = PoseConfig(
        search="always",
        suggest_next_touch=False,
        field_config=FieldConfig(cell_m=0.002),
        screened=8,
        seeds_refined=2,
        rescue_screened=30,
        rescue_refined=4,
        rescue_log_likelihood=-np.inf,  # never for the fit alone
    )
    first = pipeline.pose_from_candidates(pair, model, candidates, world, base, "match").hypotheses.probability[0]
    assert probabilities == []
    runs = {}
    for name, threshold in (("at", first), ("above", first + 0.01)):
        probabilities.clear()
        config = replace(base, rescue_probability=threshold)
        pipeline.pose_from_candidates(pair, model, candidates, world, config, "match")
        runs[name] = len(probabilities)
    assert runs == {"at": 0, "above": 1}


def test_the_sensor_pose_error_options_keep_their_old_names():
    """`--sensor-pose-error-*` (the mocap calibration's error) is not the GelSight `--calibration` file; the old
    `--calibration-error-*` names still parse to the same settings."""
    from yoto.cli import build_parser

    parser = build_parser()
    new = parser.parse_args(["pose", "p.json", "--sensor-pose-error-mm", "2.5", "--sensor-pose-error-deg", "0.5"])
    old = parser.parse_args(["pose", "p.json", "--calibration-error-mm", "2.5", "--calibration-error-deg", "0.5"])
    default = parser.parse_args(["pose", "p.json", "--calibration", "mini.npz"])
    assert (new.sensor_pose_error_mm, new.sensor_pose_error_deg) == (2.5, 0.5)
    assert (old.sensor_pose_error_mm, old.sensor_pose_error_deg) == (2.5, 0.5)
    assert (default.sensor_pose_error_mm, default.calibration) == (1.0, "mini.npz")
