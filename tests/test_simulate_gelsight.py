"""The GelSight press model: analytic sphere presses, depth control, reachability, noise, the image hook."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import trimesh

from yoto.contacts import contact_in_sensor
from yoto.geometry import make_transform, normalize, random_rotations, rotation_about_axis, transform_points
from yoto.sensor.spec import GELSIGHT_MINI
from yoto.simulate.gel import GelModel, ReconstructionNoise, reconstruct_points
from yoto.simulate.press import PressConfig, PressSimulator, simulate_contact

pytest.importorskip("open3d")

RADIUS = 0.015
PIXEL = GELSIGHT_MINI.pixel_size_m
NOISE_FREE = PressConfig(noise=ReconstructionNoise.none())


@pytest.fixture(scope="module")
def sphere():
    """A 15 mm sphere, finely tessellated (faces sag at most ~1 um inside the true sphere)."""
    return trimesh.creation.icosphere(subdivisions=6, radius=RADIUS)


def looking_along(direction: np.ndarray, origin: np.ndarray, roll_rad: float = 0.0) -> np.ndarray:
    """A sensor pose at `origin` whose +z (toward the object) is `direction`."""
    z_axis = normalize(np.asarray(direction, dtype=np.float64))
    helper = np.eye(3)[np.argmin(np.abs(z_axis))]
    x_axis = normalize(np.cross(helper, z_axis))
    rotation = np.stack([x_axis, np.cross(z_axis, x_axis), z_axis], axis=1)
    return make_transform(rotation @ rotation_about_axis(np.array([0.0, 0.0, 1.0]), roll_rad), origin)


def looking_down(x: float, y: float, z: float, tilt_deg: float = 0.0) -> np.ndarray:
    """A sensor above the point (x, y), pressing along -z of the mesh, tilted about the sensor's y axis."""
    rotation = rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.pi) @ rotation_about_axis(
        np.array([0.0, 1.0, 0.0]), np.radians(tilt_deg)
    )
    return make_transform(rotation, [x, y, z])


def sphere_press(sphere, rng, depth, gel=GelModel()):
    """Press the sphere from a random direction with the pad centre offset from the apex."""
    direction = normalize(rng.normal(size=3))
    T_start = looking_along(direction, -direction * (RADIUS + 0.003), roll_rad=rng.uniform(0, 2 * np.pi))
    offset_sensor = np.array([rng.uniform(-0.002, 0.002), rng.uniform(-0.002, 0.002), 0.0])
    T_start[:3, 3] -= T_start[:3, :3] @ offset_sensor  # the apex appears at +offset in the sensor frame
    simulator = PressSimulator(sphere, dataclasses.replace(NOISE_FREE, gel=gel))
    press = simulator.press(T_start, depth)
    return press, offset_sensor[:2]


def test_sphere_press_matches_the_spherical_cap(sphere, rng):
    for depth in (0.0005, 0.001, 0.0015):
        press, centre_xy = sphere_press(sphere, rng, depth)
        assert press.accepted, press.rejection
        x, y = GELSIGHT_MINI.pixel_xy_sensor()
        r2 = (x - centre_xy[0]) ** 2 + (y - centre_xy[1]) ** 2
        cap = (RADIUS - depth) - np.sqrt(np.maximum(RADIUS**2 - r2, 0.0))
        touching = press.contact_mask
        # Where the gel touches, it is the sphere (error: the tessellation's sag, about 1 um).
        assert np.abs(press.height_map_m[touching] - cap[touching]).max() < 3e-6
        # The press stops at its depth, measured at the deepest point.
        assert press.height_map_m.min() == pytest.approx(-depth, abs=1e-7)
        assert press.details["max_penetration_mm"] == pytest.approx(depth * 1e3, abs=1e-4)
        # The gel never lies in front of the object (it cannot penetrate it), and is nowhere above z = 0.
        assert np.all(press.height_map_m <= np.minimum(press.object_z_m, 0.0) + 1e-7)
        # Ground truth: the sphere's apex toward the sensor, at (cx, cy, -depth) in the sensor frame.
        assert np.allclose(press.p_sensor, [*centre_xy, -depth], atol=1e-5)
        assert np.linalg.norm(press.p_object) == pytest.approx(RADIUS, abs=2e-6)


def test_contact_radius_without_gel_spreading_is_the_geometric_one(sphere, rng):
    """With no sink-in, the contact is the disc where the sphere pierces the gel by more than the threshold."""
    gel = GelModel(spread_sigma_m=0.0)
    for depth in (0.0005, 0.001, 0.0015):
        press, _ = sphere_press(sphere, rng, depth, gel)
        cut = depth - gel.contact_threshold_m
        expected_radius = np.sqrt(2 * RADIUS * cut - cut**2)
        radius = np.sqrt(press.contact_pixels * PIXEL**2 / np.pi)
        assert radius == pytest.approx(expected_radius, abs=0.3 * PIXEL)


def test_gel_spreading_shrinks_the_contact_and_sinks_in_around_it(sphere, rng):
    depth = 0.001
    press_rigid, _ = sphere_press(sphere, np.random.default_rng(1), depth, GelModel(spread_sigma_m=0.0))
    press_gel, _ = sphere_press(sphere, np.random.default_rng(1), depth, GelModel())
    assert press_gel.contact_pixels < press_rigid.contact_pixels
    shrink_m = np.sqrt(press_rigid.contact_pixels * PIXEL**2 / np.pi) - np.sqrt(
        press_gel.contact_pixels * PIXEL**2 / np.pi
    )
    assert 0.05e-3 < shrink_m < 1e-3
    # Beside the contact the gel is pulled below the undeformed surface (sink-in) but not onto the object.
    beside = ~press_gel.contact_mask & (press_gel.height_map_m < -1e-5)
    assert beside.sum() > 1000
    assert np.all(press_gel.height_map_m[beside] < press_gel.object_z_m[beside])


def test_ground_truth_agrees_with_the_solvers_contact_estimate(sphere, rng):
    for _ in range(3):
        press, _ = sphere_press(sphere, rng, rng.uniform(0.0005, 0.0015))
        p_sensor, n_sensor = contact_in_sensor(press.contact_points_sensor())
        assert np.linalg.norm(p_sensor - press.p_sensor) < 2e-5
        # The sphere's outward normal at the apex faces the sensor: -z.
        assert np.degrees(np.arccos(np.clip(-n_sensor[2], -1.0, 1.0))) < 0.5
        # Mapped to the object, the estimate is on the sphere.
        assert np.linalg.norm(transform_points(press.T_object_sensor, p_sensor)) == pytest.approx(RADIUS, abs=2e-5)


def test_depth_sets_the_maximum_penetration_on_a_builtin_object(builtin_models, rng):
    model = builtin_models["figurine"]
    simulator = PressSimulator(model.mesh_object, NOISE_FREE)
    checked = 0
    while checked < 6:
        p_object = simulator.sample_surface(rng)[0]
        contact = simulate_contact(simulator, p_object, model.aggregated_normal(p_object), rng)
        if not contact.accepted:
            continue
        depth = contact.press.depth_m
        assert 0.0005 <= depth <= 0.0015
        assert -contact.press.height_map_m.min() == pytest.approx(depth, abs=1e-7)
        assert contact.press.details["max_penetration_mm"] == pytest.approx(depth * 1e3, abs=1e-4)
        # Noise-free: the tactile cloud is the contact patch, z in [-depth, -threshold].
        z = contact.points_sensor[:, 2]
        assert z.min() == pytest.approx(-depth, abs=1e-7) and z.max() < 0
        # The ground truth lies on the mesh.
        on_mesh = simulator.closest_surface_points(contact.press.p_object[None])[0]
        assert np.linalg.norm(on_mesh - contact.press.p_object) < 1e-6
        checked += 1


# ------------------------------------------------------------------------------------------ reachability
def test_a_narrow_slot_is_rejected_but_the_top_beside_it_is_not():
    block = trimesh.creation.box([0.06, 0.06, 0.03])  # top face at z = 0.015
    slot = trimesh.creation.box([0.003, 0.08, 0.02])
    slot.apply_translation([0.0, 0.0, 0.015])  # 3 mm wide, 10 mm deep: bottom at z = 0.005
    simulator = PressSimulator(trimesh.boolean.difference([block, slot], engine="manifold"), NOISE_FREE)
    bottom = np.array([0.0, 0.0, 0.005])
    press = simulator.press(looking_down(0.0, 0.0, 0.02), 0.001, target_object=bottom)
    assert press.rejection == "target_not_in_contact"
    # Aimed at a slot wall, along the wall's normal: the opposite wall hides it.
    wall = np.array([0.0015, 0.0, 0.01])
    T_wall = looking_along(np.array([1.0, 0.0, 0.0]), wall - np.array([0.001, 0.0, 0.0]))
    assert simulator.press(T_wall, 0.001, target_object=wall).rejection == "target_occluded"
    top = np.array([0.02, 0.0, 0.015])
    press = simulator.press(looking_down(0.02, 0.0, 0.02), 0.001, target_object=top)
    assert press.accepted, press.rejection
    assert press.contact_pixels > 0.9 * GELSIGHT_MINI.width_px * GELSIGHT_MINI.height_px


def test_a_thin_plate_edge_is_rejected_a_thick_one_is_not():
    for thickness, expected in ((0.0015, "thin_edge"), (0.004, None)):
        plate = trimesh.creation.box([thickness, 0.06, 0.04])  # edge face at z = 0.02, longer than the pad
        simulator = PressSimulator(plate, NOISE_FREE)
        press = simulator.press(looking_down(0.0, 0.0, 0.025), 0.001, target_object=np.array([0.0, 0.0, 0.02]))
        assert press.rejection == expected
        assert press.details["contact_width_mm"] == pytest.approx(thickness * 1e3, rel=0.05)


def test_a_big_flat_face_fills_the_pad_and_is_accepted_until_the_housing_touches():
    simulator = PressSimulator(trimesh.creation.box([0.1, 0.1, 0.04]), NOISE_FREE)
    flat = simulator.press(looking_down(0.0, 0.0, 0.025), 0.001)
    assert flat.accepted and flat.contact_pixels == GELSIGHT_MINI.width_px * GELSIGHT_MINI.height_px
    # Tilted about the sensor y axis the pad touches along one edge; the housing face (2 mm behind the gel,
    # 16 mm from the centre vs the pad's 10.15 mm) reaches the face at tan(tilt) > (2 - 1) / 5.85, ~9.7 deg.
    assert simulator.press(looking_down(0.0, 0.0, 0.025, tilt_deg=8.0), 0.001).accepted
    tilted = simulator.press(looking_down(0.0, 0.0, 0.025, tilt_deg=11.0), 0.001)
    assert tilted.rejection == "housing_collision" and tilted.details["collision"] == "housing"


def test_a_wall_beside_the_pad_hits_the_housing():
    floor = trimesh.creation.box([0.1, 0.1, 0.02])  # top at z = 0.01
    wall = trimesh.creation.box([0.02, 0.1, 0.04])
    wall.apply_translation([0.013 + 0.01, 0.0, 0.02])  # inner face at x = 13 mm: beyond the pad, inside the housing
    simulator = PressSimulator(trimesh.util.concatenate([floor, wall]), NOISE_FREE)
    press = simulator.press(looking_down(0.0, 0.0, 0.015), 0.001, target_object=np.array([0.0, 0.0, 0.01]))
    assert press.rejection == "housing_collision"
    # Far enough from the wall (housing edge at 16 mm < 30 mm - 13 mm), the same press is fine.
    press = simulator.press(looking_down(-0.018, 0.0, 0.015), 0.001, target_object=np.array([-0.018, 0.0, 0.01]))
    assert press.accepted, press.rejection


def test_a_sharp_tip_gives_too_small_a_contact():
    cone = trimesh.creation.cone(radius=0.01, height=0.02, sections=64)  # apex at z = 0.02, half-angle 26.6 deg
    simulator = PressSimulator(cone, NOISE_FREE)
    press = simulator.press(looking_down(0.0, 0.0, 0.025), 0.0005, target_object=np.array([0.0, 0.0, 0.02]))
    assert press.rejection == "small_contact"
    assert press.details["contact_pixels"] < 100


def test_an_open_mesh_seen_from_inside_is_rejected_for_back_faces(sphere):
    bowl = sphere.copy()
    bowl.update_faces(bowl.triangles_center[:, 2] < 0.5 * RADIUS)  # cut the top off: a 13 mm wide opening
    simulator = PressSimulator(bowl, NOISE_FREE)
    press = simulator.press(looking_down(0.0, 0.0, 0.03), 0.001)
    assert press.rejection == "back_face"


# ------------------------------------------------------------------------------------------ noise and hooks
def test_noise_free_reconstruction_is_the_contact_patch(sphere, rng):
    press, _ = sphere_press(sphere, rng, 0.001)
    points, _ = reconstruct_points(press.height_map_m, press.contact_mask, ReconstructionNoise.none(), rng)
    assert np.array_equal(points, press.contact_points_sensor())


def test_noise_components_have_their_configured_size(sphere, rng):
    press, _ = sphere_press(sphere, rng, 0.0015)
    clean = press.height_map_m
    mask = press.contact_mask
    # A negative threshold and no margin keep exactly the contact pixels, so errors line up with them.
    pixel_only = ReconstructionNoise(
        pixel_std_m=2e-5, bias_std_m=0.0, scale_std=0.0, mask_threshold_m=-1.0, mask_margin_px=0
    )
    points, _ = reconstruct_points(clean, mask, pixel_only, rng)
    assert len(points) == mask.sum()
    assert (points[:, 2] - clean[mask]).std() == pytest.approx(2e-5, rel=0.05)
    scale_only = ReconstructionNoise(
        pixel_std_m=0.0, bias_std_m=0.0, scale_std=0.05, mask_threshold_m=-1.0, mask_margin_px=0
    )
    points, drawn = reconstruct_points(clean, mask, scale_only, rng)
    assert np.allclose(points[:, 2], clean[mask] * (1 + drawn["scale_error"]))
    # Defaults: depth errors of a few hundredths of a millimetre over the contact.
    points, drawn = reconstruct_points(clean, mask, ReconstructionNoise(), np.random.default_rng(3))
    columns = np.rint(points[:, 0] / PIXEL + (GELSIGHT_MINI.width_px - 1) / 2).astype(int)
    rows = np.rint(points[:, 1] / PIXEL + (GELSIGHT_MINI.height_px - 1) / 2).astype(int)
    error = points[:, 2] - clean[rows, columns]
    assert 5e-6 < np.sqrt(np.mean(error**2)) < 1e-4
    # The noisy mask follows the contact: mostly the same pixels.
    noisy_mask = np.zeros_like(mask)
    noisy_mask[rows, columns] = True
    assert (noisy_mask & mask).sum() > 0.9 * mask.sum()
    assert (noisy_mask & ~mask).sum() < 0.3 * mask.sum()


def test_an_error_drawn_but_not_applied_leaves_the_other_draws_as_they_were(sphere, rng):
    """`not_applied` (the tracking benchmark's `--without`): the part is drawn and left out, so the errors left on are
    the very draws of the run with every part on (a standard deviation of 0 would skip the draw and change them)."""
    from dataclasses import replace

    press, _ = sphere_press(sphere, rng, 0.0015)
    clean, mask = press.height_map_m, press.contact_mask
    exact = ReconstructionNoise(mask_threshold_m=-1.0, mask_margin_px=0)  # every contact pixel kept, in order

    def error(noise: ReconstructionNoise) -> np.ndarray:
        points, _ = reconstruct_points(clean, mask, noise, np.random.default_rng(5))
        return points[:, 2] - clean[mask]

    every = error(exact)
    no_pixel, no_bias, no_scale = (error(replace(exact, not_applied=(part,))) for part in ("pixel", "bias", "scale"))
    pixel = every - no_pixel  # the pixel noise alone: white, of its configured size
    assert pixel.std() == pytest.approx(exact.pixel_std_m, rel=0.05)
    # without the smooth field: the same scale error and pixel noise, so what it takes off is smooth (neighbouring
    # pixels within a few percent of its size; any other pixel noise would leave white noise of 15 um in it)
    bias = every - no_bias
    assert 0.3 * exact.bias_std_m < bias.std() < 3.0 * exact.bias_std_m
    assert np.median(np.abs(np.diff(bias))) < 0.05 * exact.bias_std_m
    # without the scale error: exactly the scale's share taken off, field and pixel noise as they were
    scale = every - no_scale
    np.testing.assert_allclose(scale, clean[mask] * (scale / clean[mask]).mean(), atol=1e-15)
    # a zero standard deviation skips the draw instead: the pixel noise then comes from other draws
    zeroed = error(replace(exact, bias_std_m=0.0))
    assert not np.allclose(zeroed, no_bias, atol=1e-7)


def test_reconstruct_hook_receives_the_noise_free_height_map(builtin_models, rng):
    model = builtin_models["fruit"]
    simulator = PressSimulator(model.mesh_object)
    seen = []

    def reconstruct(height_map_m: np.ndarray) -> np.ndarray:
        seen.append(height_map_m)
        mask = height_map_m < -1e-4
        return GELSIGHT_MINI.height_map_to_points(height_map_m, mask) + np.array([0.0, 0.0, 1e-6])

    for _ in range(50):
        p_object = simulator.sample_surface(rng)[0]
        contact = simulate_contact(simulator, p_object, model.aggregated_normal(p_object), rng, reconstruct=reconstruct)
        if contact.accepted:
            break
    assert contact.accepted and len(seen) == 1
    assert seen[0].shape == (240, 320) and seen[0] is contact.press.height_map_m
    expected = GELSIGHT_MINI.height_map_to_points(seen[0], seen[0] < -1e-4) + np.array([0.0, 0.0, 1e-6])
    assert np.array_equal(contact.points_sensor, expected)


def test_approach_directions_respect_the_tilt_limit(builtin_models, rng):
    model = builtin_models["fruit"]
    simulator = PressSimulator(model.mesh_object, dataclasses.replace(NOISE_FREE, max_tilt_deg=10.0))
    tilts, rolls = [], []
    for rotation in random_rotations(rng, 300):
        normal = rotation[:, 0]
        T, depth, drawn = simulator.draw_approach(np.zeros(3), normal, rng)
        tilt = np.degrees(np.arccos(np.clip(T[:3, 2] @ -normal, -1, 1)))
        assert tilt == pytest.approx(drawn["tilt_deg"], abs=1e-6) and tilt <= 10.0 + 1e-9
        assert 0.5 <= drawn["depth_mm"] <= 1.5
        assert drawn["offset_mm"] <= 1.5
        tilts.append(tilt)
        rolls.append(drawn["roll_deg"])
    # Uniform on the cap: P(tilt < 10 / sqrt(2) deg) is about one half.
    assert 0.4 < np.mean(np.array(tilts) < 10 / np.sqrt(2)) < 0.6
    assert np.ptp(rolls) > 300
