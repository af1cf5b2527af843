"""The refinement: its normal equations against finite differences of the clouds' residuals, and which poses the
pose stage refines in full."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import trimesh
from conftest import TOL

from yoto.geometry import (
    invert_transform,
    make_transform,
    random_rotations,
    rotation_about_axis,
    se3_exp,
    transform_points,
)
from yoto.objects.model import ObjectModelConfig, build_object_model
from yoto.objects.symmetry import Symmetry
from yoto.pose.field import surface_field
from yoto.pose.pipeline import PoseConfig, _best_distinct, _verify_and_refine
from yoto.pose.refine import (
    CalibrationPrior,
    ContactPoints,
    RefineConfig,
    _add_normal_equations,
    contact_points,
    evaluate_offsets,
    refine_hypotheses,
    thinned,
)
from yoto.registration import transform_batch


@pytest.fixture(scope="module")
def box():
    return build_object_model(
        trimesh.creation.box(extents=(0.12, 0.08, 0.05)), "box", ObjectModelConfig(num_points=20_000)
    )


def _box_contacts(box, T_world_object: np.ndarray, points: int = 40) -> list[ContactPoints]:
    """Two contacts on two faces of the box, away from its edges, each in its own sensor frame."""
    contacts = []
    centre_object = transform_points(box.T_object_mesh, np.array([[0.01, 0.005, 0.025], [0.06, -0.01, 0.0]]))
    for sensor, (centre, normal) in enumerate(zip(centre_object, ([0, 0, 1.0], [1.0, 0, 0]))):
        patch = box.points_object[np.linalg.norm(box.points_object - centre, axis=1) < 0.005][:points]
        T_object_sensor = make_transform(rotation_about_axis(np.array(normal), 0.7 + sensor), centre)
        points_sensor = transform_batch(invert_transform(T_object_sensor)[None], patch)[0]
        contacts.append(ContactPoints(points_sensor, T_world_object @ T_object_sensor, sensor, np.zeros((0, 3))))
    return contacts


def test_normal_equations_match_finite_differences(box, rng):
    """Both sensors' correction rows come from the object pose's rows by the adjoint (refine.py): the system they
    give must be J^T W J and J^T W r of the Jacobian measured by finite differences of the residuals. On a box's
    faces, away from its edges, the distance field is linear, so the finite differences are exact."""
    field = surface_field(box)
    T_world_object = make_transform(random_rotations(rng, 1)[0], [0.4, -0.1, 0.3])
    contacts = _box_contacts(box, T_world_object)
    poses = T_world_object @ se3_exp(rng.normal(scale=[0.003] * 3 + [0.0003] * 3, size=(3, 6)))
    corrections = se3_exp(rng.normal(scale=[0.01] * 3 + [0.0005] * 3, size=(3, 2, 6)))
    config = RefineConfig(surface_noise_m=0.01)  # every residual within the robust scale: all weights 1 / noise^2
    hessian, gradient = np.zeros((3, 18, 18)), np.zeros((3, 18))
    _add_normal_equations(field, contacts, poses, corrections, config, hessian, gradient)

    def residuals(twist: np.ndarray) -> np.ndarray:
        """(K, points) every contact's residual after moving the pose and corrections by `twist` (K, 18)."""
        moved = poses @ se3_exp(twist[:, :6])
        corrected = corrections @ se3_exp(twist[:, 6:].reshape(-1, 2, 6))
        parts = []
        for contact in contacts:
            A = np.linalg.inv(moved) @ contact.T_world_sensor @ corrected[:, contact.sensor]
            parts.append(field.distance(transform_batch(A, contact.points_sensor), with_gradient=False)[0])
        return np.concatenate(parts, axis=1)

    step = 1e-4  # the field interpolates in float32 (~1e-8 m): a step that moves points by micrometres
    twists = np.broadcast_to(step * np.eye(18)[:, None], (18, 3, 18))  # one coordinate moved, every pose
    jacobian = np.stack([(residuals(t) - residuals(-t)) / (2 * step) for t in twists], axis=-1)  # (K, points, 18)
    weight = 1.0 / config.surface_noise_m**2
    expected = weight * np.swapaxes(jacobian, 1, 2) @ jacobian
    assert np.abs(hessian - expected).max() < 1e-4 * np.abs(expected).max()
    expected_gradient = weight * np.einsum("kpi,kp->ki", jacobian, residuals(np.zeros((3, 18))))
    assert np.abs(gradient - expected_gradient).max() < 1e-4 * np.abs(expected_gradient).max()
    # The corrections' blocks are not zero: the test sees them.
    assert np.abs(hessian[:, 6:12, 6:12]).max() > 0.1 * np.abs(expected).max()
    assert np.abs(hessian[:, 12:, 12:]).max() > 0.1 * np.abs(expected).max()


def test_neighbours_are_refined_only_when_the_first_hypothesis_is_not_decisive(box, rng):
    """The neighbours of the most likely hypotheses are refined unless the first already holds
    `decisive_probability` and fits to `decisive_log_likelihood`; then the seeds' full refinement is all there is,
    and where they are refined, the seeds' part is the same."""
    field = surface_field(box)
    T_world_object = make_transform(random_rotations(rng, 1)[0], [0.4, -0.1, 0.3])
    contacts = _box_contacts(box, T_world_object, points=120)
    seeds = T_world_object @ se3_exp(rng.normal(scale=[0.05] * 3 + [0.004] * 3, size=(60, 6)))
    seeds[0] = T_world_object

    def refined(**settings) -> np.ndarray:
        config = PoseConfig(**settings)
        return _verify_and_refine(field, contacts, seeds, Symmetry(), config, 30, 8, neighbours=True).T_world_object

    decisive = refined(decisive_probability=0.0, decisive_log_likelihood=-np.inf, neighbours_if_decisive=False)
    undecided = refined(decisive_probability=1.01, neighbours_if_decisive=False)
    forced = refined(decisive_probability=0.0, decisive_log_likelihood=-np.inf)  # the default refines them anyway
    assert len(decisive) <= 8 and len(undecided) > len(decisive) + 8
    assert np.array_equal(undecided[: len(decisive)], decisive)
    assert np.array_equal(forced, undecided)
    # The true pose was a seed: its refinement stayed there.
    assert np.linalg.norm(decisive[:, :3, 3] - T_world_object[:3, 3], axis=1).min() < 5e-4


def test_field_reads_the_box_inside_and_the_band_outside_its_grid(box, rng):
    """On the box's faces, away from its edges, the field is the signed distance to the nearest face with that
    face's normal; points beyond the grid on any side (negative indices included) read +band with a zero normal
    (the reads there are clipped into the grid, then masked)."""
    field = surface_field(box)
    half = np.array([0.06, 0.04, 0.025])
    T_object_mesh = box.T_object_mesh
    depth = rng.uniform(-0.002, 0.002, size=50)
    p_mesh = np.column_stack([rng.uniform(-0.03, 0.03, 50), rng.uniform(-0.02, 0.02, 50), half[2] + depth])
    distance, normal = field.distance(transform_points(T_object_mesh, p_mesh))
    assert np.abs(distance - depth).max() < TOL["float32"]
    assert np.abs(normal - T_object_mesh[:3, 2]).max() < 10 * TOL["float32_unit"]  # differences of float32 values
    outside = field.origin + np.array([[-1.0, 0.0, 0.0], [0.0, -0.5, 0.0], [0.0, 0.0, 2.0], [5.0, 5.0, -5.0]])
    far, far_normal = field.distance(np.vstack([outside, transform_points(T_object_mesh, p_mesh[:2])]))
    assert np.array_equal(far[:4], np.full(4, field.band_m)) and not far_normal[:4].any()
    assert np.abs(far[4:] - depth[:2]).max() < TOL["float32"]


def test_depth_scale_rows_match_finite_differences(box, rng):
    """A contact with a depth-scale prior adds one parameter, its log scale, acting on the heights (sensor z) about
    the pad plane: its rows and its coupling to the pose and the corrections must be those of finite differences."""
    field = surface_field(box)
    T_world_object = make_transform(random_rotations(rng, 1)[0], [0.4, -0.1, 0.3])
    contacts = []
    for contact in _box_contacts(box, T_world_object):
        points = contact.points_sensor + [0.0, 0.0, -0.001] + rng.normal(scale=2e-4, size=contact.points_sensor.shape)
        contacts.append(ContactPoints(points, contact.T_world_sensor, contact.sensor, contact.free_sensor, 0.1))
    poses = T_world_object @ se3_exp(rng.normal(scale=[0.003] * 3 + [0.0003] * 3, size=(3, 6)))
    corrections = se3_exp(rng.normal(scale=[0.01] * 3 + [0.0005] * 3, size=(3, 2, 6)))
    log_scale = rng.normal(scale=0.2, size=(3, 2))
    config = RefineConfig(surface_noise_m=0.01)
    hessian, gradient = np.zeros((3, 20, 20)), np.zeros((3, 20))
    _add_normal_equations(field, contacts, poses, corrections, config, hessian, gradient, np.exp(log_scale))

    def residuals(change: np.ndarray) -> np.ndarray:
        moved = poses @ se3_exp(change[:, :6])
        corrected = corrections @ se3_exp(change[:, 6:18].reshape(-1, 2, 6))
        parts = []
        for c, contact in enumerate(contacts):
            scale = np.exp(log_scale[:, c] + change[:, 18 + c])
            points = np.broadcast_to(contact.points_sensor, (3,) + contact.points_sensor.shape).copy()
            points[..., 2] *= scale[:, None]
            A = np.linalg.inv(moved) @ contact.T_world_sensor @ corrected[:, contact.sensor]
            parts.append(field.distance(transform_batch(A, points), with_gradient=False)[0])
        return np.concatenate(parts, axis=1)

    step = 1e-4
    changes = np.broadcast_to(step * np.eye(20)[:, None], (20, 3, 20))
    jacobian = np.stack([(residuals(t) - residuals(-t)) / (2 * step) for t in changes], axis=-1)
    weight = 1.0 / config.surface_noise_m**2
    expected = weight * np.swapaxes(jacobian, 1, 2) @ jacobian
    assert np.abs(hessian - expected).max() < 1e-4 * np.abs(expected).max()
    expected_gradient = weight * np.einsum("kpi,kp->ki", jacobian, residuals(np.zeros((3, 20))))
    assert np.abs(gradient - expected_gradient).max() < 1e-4 * np.abs(expected_gradient).max()
    diagonal = np.sqrt(np.diagonal(hessian, axis1=1, axis2=2))
    correlation = hessian / (diagonal[:, :, None] * diagonal[:, None, :])
    assert np.abs(correlation[:, 18:, :18]).max() > 0.3  # the scale is coupled to the pose: the test sees it


@pytest.fixture(scope="module")
def ellipsoid():
    mesh = trimesh.creation.icosphere(subdivisions=5)
    mesh.apply_scale([0.04, 0.025, 0.018])
    return build_object_model(mesh, "ellipsoid", ObjectModelConfig(num_points=20_000))


def _pressed_contacts(model, T_world_object, depth_m: float, true_scale: list[float], sigma: float):
    """Two presses `depth_m` deep on opposite sides of a curved object, each cloud's heights read `true_scale` times
    too shallow (as an image reconstruction might), in sensors whose -z looks along the outward normal."""
    contacts = []
    for sensor, direction in enumerate(([1.0, 0.3, 0.2], [-0.8, -0.2, 0.5])):
        distance, index = model.kdtree.query(0.05 * np.array(direction))
        p0, n_out = model.points_object[index], model.normals_object[index]
        z_axis = -n_out
        x_axis = np.cross(z_axis, [0.0, 0.0, 1.0])
        x_axis /= np.linalg.norm(x_axis)
        rotation = np.column_stack([x_axis, np.cross(z_axis, x_axis), z_axis])
        T_object_sensor = make_transform(rotation, p0 - depth_m * n_out)
        local = transform_batch(invert_transform(T_object_sensor)[None], model.points_object)[0]
        cap = local[(local[:, 2] <= 0) & (np.linalg.norm(local[:, :2], axis=1) < 0.006)]
        measured = cap * [1.0, 1.0, 1.0 / true_scale[sensor]]
        contacts.append(
            contact_points(
                measured, T_world_object @ T_object_sensor, sensor, model.point_spacing_m, RefineConfig(), sigma
            )
        )
    return contacts


def test_depth_scale_is_recovered_and_clean_contacts_keep_theirs(ellipsoid, rng):
    """Clouds whose heights came back 25% and 10% too shallow: with a depth-scale prior the refinement at the true
    pose finds both scales (within 3%) and fits better than taking the heights as exact; with none (sigma 0, clean
    clouds) every scale stays exactly 1."""
    field = surface_field(ellipsoid)
    T_world_object = make_transform(random_rotations(rng, 1)[0], [0.2, 0.1, 0.3])
    truth = [1.25, 1.1]
    scaled = _pressed_contacts(ellipsoid, T_world_object, 0.0012, truth, 0.2)
    exact = _pressed_contacts(ellipsoid, T_world_object, 0.0012, truth, 0.0)
    prior = CalibrationPrior()
    with_scale = refine_hypotheses(field, scaled, T_world_object[None], prior, RefineConfig())
    without = refine_hypotheses(field, exact, T_world_object[None], prior, RefineConfig())
    assert np.abs(with_scale.depth_scale[0] / truth - 1).max() < 0.03
    assert np.array_equal(without.depth_scale, np.ones((1, 2)))
    assert with_scale.fit_rms_m.max() < 0.5 * without.fit_rms_m.max()
    # The scale's prior is part of the corrections' cost: |log 1.25| / 0.2 ~ 1.1 sigma squared.
    assert with_scale.correction_cost[0] > (np.log(1.2) / 0.2) ** 2


def test_field_reads_a_thin_wall_within_a_few_microns():
    """At a wall 1.5 mm thick (a mug's), a grid of 1 mm cells interpolates across the wall's middle, where the
    distance turns back towards the other face: its reads at the outer face were 27 um RMS off the mesh, most of a
    right pose's residual (30 um). The default grid (0.5 mm) reads within a few microns."""
    from yoto.pose.field import FieldConfig, build_surface_field

    tube = build_object_model(
        trimesh.creation.annulus(r_min=0.0185, r_max=0.02, height=0.03, sections=256),
        "tube",
        ObjectModelConfig(num_points=20_000),
    )
    rng = np.random.default_rng(0)
    angle, height = rng.uniform(0.0, 2.0 * np.pi, 400), rng.uniform(-0.01, 0.01, 400)
    radius = 0.02 + rng.uniform(-0.0002, 0.0002, 400)  # within 0.2 mm of the outer face
    points = transform_points(
        tube.T_object_mesh, np.column_stack([radius * np.cos(angle), radius * np.sin(angle), height])
    )
    closest, normals = tube.raycaster.closest_points_and_normals(points)
    offset = points - closest
    exact = np.sign(np.einsum("ij,ij->i", offset, normals)) * np.linalg.norm(offset, axis=1)

    def error_rms(field_config: FieldConfig) -> float:
        distance, _ = build_surface_field(tube, field_config).distance(points, with_gradient=False)
        return float(np.sqrt(np.mean((distance - exact) ** 2)))

    assert error_rms(FieldConfig()) < 5e-6
    assert error_rms(FieldConfig(cell_m=0.001)) > 15e-6


def test_the_full_refinement_starts_where_the_short_one_left_the_sensor_corrections(box, rng):
    """Each pose the short refinement screened is refined in full from its own sensor corrections
    (`full_from_screen_corrections`), not from none: what `_verify_and_refine` returns is the full refinement of the
    chosen short-refined poses started from their corrections, and it differs from the one started from none."""
    field = surface_field(box)
    T_world_object = make_transform(random_rotations(rng, 1)[0], [0.4, -0.1, 0.3])
    contacts = _box_contacts(box, T_world_object, points=120)
    error = se3_exp(np.array([0.015, -0.01, 0.01, 0.0008, -0.0006, 0.0]))  # each reported sensor pose this far off
    contacts = [replace(contact, T_world_sensor=contact.T_world_sensor @ error) for contact in contacts]
    seeds = T_world_object @ se3_exp(rng.normal(scale=[0.03] * 3 + [0.002] * 3, size=(40, 6)))
    config = PoseConfig()
    refine = config.refine_config
    carried = _verify_and_refine(field, contacts, seeds, Symmetry(), config, 20, 6)
    from_none = _verify_and_refine(
        field, contacts, seeds, Symmetry(), PoseConfig(full_from_screen_corrections=False), 20, 6
    )
    # The same steps by hand: the short refinement of the best 20 by the cheap score, its 6 best distinct poses.
    chosen = np.argsort(-evaluate_offsets(field, contacts, seeds, config.calibration, refine), kind="stable")[:20]
    screening = thinned(contacts, refine.screen_points, refine.screen_free_points)
    short = refine_hypotheses(
        field, screening, seeds[chosen], config.calibration, replace(refine, iterations=refine.screen_iterations)
    )
    best = _best_distinct(short, Symmetry(), config.hypotheses, 6)
    expected = refine_hypotheses(
        field, contacts, short.T_world_object[best], config.calibration, refine, short.corrections[best]
    )
    assert np.array_equal(carried.T_world_object, expected.T_world_object)
    assert np.array_equal(carried.corrections, expected.corrections)
    none = refine_hypotheses(field, contacts, short.T_world_object[best], config.calibration, refine)
    assert np.array_equal(from_none.T_world_object, none.T_world_object)
    assert not np.array_equal(carried.corrections, from_none.corrections)


def _ridge_field(half_width: float = 0.001, cell: float = 0.0001, band: float = 0.004):
    """The signed distance of a wall 2 * half_width thick (along x), its top face at z = 0, on a grid."""
    from yoto.pose.field import SurfaceField

    across = np.arange(-0.005, 0.005 + 1e-9, cell)
    axes = [across, across, np.arange(-0.008, 0.002, cell)]
    x, y, z = np.meshgrid(*axes, indexing="ij")
    q = np.stack([np.abs(x) - half_width, np.abs(y) - 0.02, np.abs(z + 0.01) - 0.01], axis=-1)  # a box |y| < 20 mm
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    values = np.clip(outside + np.minimum(q.max(axis=-1), 0.0), -band, band).astype(np.float32)
    return SurfaceField(np.array([axis[0] for axis in axes]), cell, values, band, 0.0)


@pytest.mark.parametrize("compiled", [True, False])
def test_the_gels_skirt_beside_a_ridge_is_forgiven_and_a_hovering_cloud_is_not(monkeypatch, compiled):
    """A pad pressed 0.3 mm onto a ridge 2 mm wide: the gel sinks in beside it (its skirt hangs in the air over the
    drop, up to 0.6 mm from the wall). The skirt's points count at most `skirt_tau_m`; a cloud hovering 150 um over
    the ridge's top (the object reaches the pad plane under it) and one floating clear of it (nothing touches)
    count in full."""
    import yoto.pose.field as field_module
    import yoto.pose.refine as refine_module
    from yoto.pose.refine import evaluate_fit

    if not compiled:
        monkeypatch.setattr(field_module, "KERNELS", None)
        monkeypatch.setattr(refine_module, "KERNELS", None)
    field, press = _ridge_field(), 0.0003
    x, y = np.meshgrid(np.linspace(-0.0016, 0.0016, 33), np.linspace(-0.002, 0.002, 9))
    x, y = x.ravel(), y.ravel()
    beyond = np.maximum(np.abs(x) - 0.001, 0.0)  # how far beyond the ridge's side
    depth = np.where(beyond > 0, 0.6 * press * np.exp(-((beyond / 0.0004) ** 2)), press)
    points_sensor = np.column_stack([x, y, -depth])  # heights below the pad plane: negative
    # sensor -> object: the pad faces down onto the ridge (sensor z is object -z), the pad plane at z = -press
    T_object_sensor = make_transform(rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.pi), [0.0, 0.0, -press])
    skirt_config, plain_config = RefineConfig(), RefineConfig(skirt_tau_m=None)

    def rms(points: np.ndarray, lift: float, config: RefineConfig) -> float:
        T = T_object_sensor.copy()
        T[2, 3] += lift  # the pad moved away from the ridge
        contacts = [ContactPoints(points, T, 0, np.zeros((0, 3)))]
        return float(evaluate_fit(field, contacts, np.eye(4)[None], None, config)[0][0, 0])

    # the skirt's exact distances: to the ridge's side (its points lie below the top face)
    distance = beyond
    expected = np.sqrt(np.mean(np.minimum(distance, skirt_config.skirt_tau_m) ** 2))
    assert rms(points_sensor, 0.0, skirt_config) == pytest.approx(expected, abs=3e-6)
    assert rms(points_sensor, 0.0, plain_config) == pytest.approx(
        np.sqrt(np.mean(np.minimum(distance, plain_config.fit_tau_m) ** 2)), abs=3e-6
    )
    assert rms(points_sensor, 0.0, plain_config) > 3 * rms(points_sensor, 0.0, skirt_config)
    on_top = points_sensor[beyond == 0]
    for config in (skirt_config, plain_config):
        assert rms(on_top, 0.00015, config) == pytest.approx(0.00015, abs=3e-6)  # hovering: in full
        assert rms(points_sensor, 0.002, config) == pytest.approx(config.fit_tau_m)  # floating: nothing touches
