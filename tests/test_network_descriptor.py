"""The `cpu` network's pieces: polar height maps, the roll search, free space, anchors, roll-invariant descriptors."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

torch = pytest.importorskip("torch")

from yoto.network.anchors import make_anchor_set  # noqa: E402
from yoto.network.descriptor import DescriptorNet, invariant_feature_count, invariant_features  # noqa: E402
from yoto.network.polar import (  # noqa: E402
    ContactPolarMap,
    PolarGrid,
    RollFit,
    contact_polar_map,
    free_space_penalty,
    press_maps,
    roll_plane_search,
    roll_plane_search_reference,
)
from yoto.network.presets import PRESETS, AnchorNetConfig, NetworkConfig, network_config_from_dict  # noqa: E402
from yoto.objects.model import ObjectModelConfig, build_object_model  # noqa: E402

GRID = PolarGrid(rings=6, angles=16, ring_width_m=0.0015)
SPHERE_RADIUS_M = 0.05


def paraboloid_cloud(depth_m: float = 0.001, radius_m: float = SPHERE_RADIUS_M, pixel_m: float = 0.0001):
    """A dense tactile cloud of a sphere pressed `depth_m` into a flat gel (sensor frame: z <= 0 in contact)."""
    coords = (np.arange(int(round(0.02 / pixel_m))) - (0.01 / pixel_m - 0.5)) * pixel_m  # symmetric about 0
    x, y = (g.ravel() for g in np.meshgrid(coords, coords, indexing="ij"))
    z = (x**2 + y**2) / (2.0 * radius_m) - depth_m  # the surface, a paraboloid near the pole
    keep = z <= 0.0
    return np.stack([x[keep], y[keep], z[keep]], axis=1)


def test_polar_cells_cover_rings_of_equal_width():
    radii = np.linalg.norm(GRID.centres, axis=-1)
    np.testing.assert_allclose(radii[:, 0], (np.arange(6) + 0.5) * 0.0015)
    np.testing.assert_allclose(np.ptp(radii, axis=1), 0.0, atol=1e-15)
    angles = np.arctan2(GRID.centres[0, :, 1], GRID.centres[0, :, 0]) % (2 * np.pi)
    np.testing.assert_allclose(angles, (np.arange(16) + 0.5) * 2 * np.pi / 16)
    # Cell areas: ring i spans pi w^2 ((i+1)^2 - i^2) = pi w^2 (2i + 1), shared by its sectors.
    np.testing.assert_allclose(GRID.weights[:, 0], 2 * np.arange(6) + 1)


def test_contact_map_reads_the_surface_heights_at_the_cell_centres():
    points = paraboloid_cloud()
    contact = contact_polar_map(points, GRID, pixel_m=0.0002, erode_px=1)
    np.testing.assert_allclose(contact.centre_sensor, [0.0, 0.0, -0.001], atol=2e-5)
    np.testing.assert_allclose(contact.normal_sensor, [0.0, 0.0, -1.0], atol=2e-3)
    radii = np.linalg.norm(GRID.centres, axis=-1)
    # The contact is the disc where the paraboloid is below the gel: radius sqrt(2 R depth) = 10 mm.
    assert contact.covered[radii < 0.0095].all() and not contact.covered[radii > 0.0101].any()
    # The map's normal is fitted around the point nearest the centroid, half a pixel off the pole: a tilt of about
    # 1 mrad. Up to that plane, the heights are the paraboloid's to a micrometre (point samples at the cell centres;
    # cell means would be off by up to 13 um in the outer ring).
    error = (contact.heights_m - radii**2 / (2.0 * SPHERE_RADIUS_M))[contact.covered]
    basis = np.stack([np.ones(len(error)), GRID.centres[contact.covered][:, 0], GRID.centres[contact.covered][:, 1]], 1)
    plane = np.linalg.lstsq(basis, error, rcond=None)[0]
    assert np.abs(plane[1:]).max() < 2e-3 and np.abs(error - basis @ plane).max() < 1e-6
    # Beyond the contact, over the pad: free cells, where the gel plane lies `depth` below the centre's height.
    np.testing.assert_allclose(contact.gel_heights_m, 0.001, atol=2e-5)
    assert contact.free[radii > 0.0106].all() and not contact.free[radii < 0.0095].any()


def test_network_input_is_heights_in_the_height_unit_and_coverage():
    contact = contact_polar_map(paraboloid_cloud(), GRID, 0.0002, 1)
    maps = contact.network_input(0.001)
    assert maps.shape == (2, 6, 16) and maps.dtype == np.float32
    np.testing.assert_allclose(maps[0], np.where(contact.covered, contact.heights_m / 0.001, 0.0), atol=1e-6)
    np.testing.assert_array_equal(maps[1], contact.covered)


def random_surfaces(rng, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Smooth random height maps (N, R, T) with some cells missing."""
    radii = np.linalg.norm(GRID.centres, axis=-1)
    theta = np.arctan2(GRID.centres[..., 1], GRID.centres[..., 0])
    heights = np.zeros((count,) + radii.shape)
    for k in range(4):
        a, b = rng.normal(size=(2, count, 1, 1)) * 2e-4
        heights += (radii / 0.009) ** (k + 1) * (a * np.cos(k * theta) + b * np.sin(k * theta))
    valid = rng.random(heights.shape) > 0.1
    return np.where(valid, heights, 0.0), valid


def synthetic_contact(heights: np.ndarray, covered: np.ndarray) -> ContactPolarMap:
    free = np.zeros_like(covered)
    return ContactPolarMap(heights, covered, np.zeros(3), np.array([0, 0, -1.0]), np.eye(3), 2e-4, free, heights, 1e-4)


def test_roll_search_agrees_with_the_obvious_loop(rng):
    heights, valid = random_surfaces(rng, 5)
    covered = rng.random(heights.shape[1:]) > 0.3
    contact = synthetic_contact(rng.normal(size=heights.shape[1:]) * 1e-4, covered)
    fast = roll_plane_search(contact, GRID, heights, valid, air_penalty_m=5e-4)
    slow = roll_plane_search_reference(contact, GRID, heights, valid, air_penalty_m=5e-4)
    np.testing.assert_array_equal(fast.shift, slow.shift)
    np.testing.assert_allclose(fast.cost_m2, slow.cost_m2, rtol=1e-8, atol=1e-16)
    np.testing.assert_allclose(fast.plane, slow.plane, rtol=1e-6, atol=1e-12)


def test_roll_search_recovers_a_rolled_and_tilted_copy(rng):
    heights, _ = random_surfaces(rng, 4)
    valid = np.ones(heights.shape, dtype=bool)
    x, y = GRID.centres[..., 0], GRID.centres[..., 1]
    for target, shift in enumerate((0, 3, 9, 15)):
        plane = np.array([1e-4, 0.02, -0.01])
        # Contact cell t sees the surface's cell t + shift, lifted by a plane in the contact's frame.
        observed = np.roll(heights[target], -shift, axis=1) + plane[0] + plane[1] * x + plane[2] * y
        contact = synthetic_contact(observed, np.ones(observed.shape, dtype=bool))
        fit = roll_plane_search(contact, GRID, heights, valid, air_penalty_m=5e-4)
        assert fit.shift[target] == shift
        assert fit.cost_m2[target] < 1e-18 and fit.cost_m2[target] < 1e-3 * np.delete(fit.cost_m2, target).min()
        np.testing.assert_allclose(fit.plane[:, target], plane, atol=1e-10)


def test_free_space_counts_surface_that_would_push_into_the_gel_where_nothing_was_seen():
    covered = np.zeros((6, 16), dtype=bool)
    covered[:2] = True
    free = np.zeros_like(covered)
    free[4:] = True
    gel = np.full((6, 16), 0.001)
    contact = ContactPolarMap(
        np.zeros((6, 16)), covered, np.zeros(3), np.array([0, 0, -1.0]), np.eye(3), 2e-4, free, gel, 1e-4
    )
    heights = np.stack([np.full((6, 16), 0.002), np.full((6, 16), 0.0006)])  # beyond the gel; 0.3 mm into it
    valid = np.ones(heights.shape, dtype=bool)
    fit = RollFit(np.zeros(2), np.zeros(2, dtype=np.int64), np.zeros((3, 2)))
    penalty = free_space_penalty(contact, GRID, heights, valid, fit, cap_m=0.005)
    assert penalty[0] == 0.0
    expected = (GRID.weights[4:] * 0.0003**2).sum() / GRID.weights[:2].sum()
    assert penalty[1] == pytest.approx(expected)


def test_press_maps_keep_what_a_press_of_the_given_depth_touches():
    heights = np.array([[[0.0, 0.0005], [0.0011, -0.0002]]])
    valid = np.array([[[True, True], [True, False]]])
    maps = press_maps(heights, valid, depth_m=0.001, height_unit_m=0.001)
    np.testing.assert_array_equal(maps[0, 1], [[1, 1], [0, 0]])  # within 1 mm of the nearest valid surface (0)
    np.testing.assert_allclose(maps[0, 0], [[0.0, 0.5], [0.0, 0.0]])


@pytest.fixture(scope="module")
def sphere_model():
    mesh = trimesh.creation.icosphere(subdivisions=5, radius=SPHERE_RADIUS_M)
    return build_object_model(mesh, "sphere", ObjectModelConfig(num_points=30_000))


def test_anchors_see_the_sphere_around_them(sphere_model):
    config = AnchorNetConfig(rings=6, angles=16, ring_width_m=0.0015, anchor_spacing_m=0.006)
    anchors = make_anchor_set(sphere_model, config)
    assert 100 < len(anchors) < 2000
    np.testing.assert_allclose(np.linalg.norm(anchors.points_object, axis=1), SPHERE_RADIUS_M, atol=2e-4)
    radial = anchors.points_object / np.linalg.norm(anchors.points_object, axis=1, keepdims=True)
    outward = np.einsum("ij,ij->i", anchors.normals_object, radial)
    assert outward.min() > 0.999
    frames = anchors.frames(np.arange(len(anchors)))
    np.testing.assert_allclose(frames @ frames.transpose(0, 2, 1), np.broadcast_to(np.eye(3), frames.shape), atol=1e-9)
    assert np.linalg.det(frames).min() > 0.999  # right-handed (u, v, -n)
    radii = np.linalg.norm(GRID.centres, axis=-1)
    expected = SPHERE_RADIUS_M - np.sqrt(SPHERE_RADIUS_M**2 - radii**2)
    assert anchors.valid.all()
    assert np.abs(anchors.heights_m - expected).max() < 2.5e-4  # the anchor and tessellation lie within 0.2 mm


def test_descriptor_features_ignore_the_roll_and_see_a_mirror(rng):
    config = AnchorNetConfig(rings=6, angles=16, harmonics=5, hidden_dims=(32,), feature_dim=8)
    maps = torch.from_numpy(rng.normal(size=(3, 2, 6, 16)).astype(np.float32))
    maps[:, 1] = (maps[:, 1] > 0).float()
    features = invariant_features(maps, config.harmonics)
    assert features.shape == (3, invariant_feature_count(config))
    for shift in (1, 5, 11):
        torch.testing.assert_close(invariant_features(torch.roll(maps, shift, dims=-1), 5), features)
    mirrored = invariant_features(torch.flip(maps, dims=[-1]), 5)
    assert (mirrored - features).abs().max() > 0.1
    net = DescriptorNet(config)
    descriptors = net(maps)
    torch.testing.assert_close(descriptors.norm(dim=-1), torch.ones(3))
    torch.testing.assert_close(net(torch.roll(maps, 7, dims=-1)), descriptors)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_presets_round_trip_with_their_kind(name):
    config = PRESETS[name]
    stored = config.to_dict()
    assert stored["kind"] == {NetworkConfig: "points", AnchorNetConfig: "anchors"}[type(config)]
    assert network_config_from_dict(stored) == config
    with pytest.raises(ValueError, match="unknown network config keys"):
        network_config_from_dict({**stored, "typo": 1})
    no_kind = {k: v for k, v in stored.items() if k != "kind"}
    if isinstance(config, NetworkConfig):  # checkpoints written before networks had kinds
        assert network_config_from_dict(no_kind) == config
    with pytest.raises(ValueError, match="unknown network kind"):
        network_config_from_dict({**stored, "kind": "voxels"})
