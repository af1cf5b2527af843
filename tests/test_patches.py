"""Patch canonicalization (one function for virtual and real patches) and the virtual patch generator."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import TOL

from yoto.geometry import make_transform, random_rotations, rotate_vectors, rotation_about_axis, transform_points
from yoto.patches.canonical import canonicalize_patch, prepare_tactile_cloud
from yoto.patches.virtual import VirtualPatchConfig, VirtualPatchDataset, generate_virtual_patches, variant_angles_rad

SMALL = VirtualPatchConfig(fixed_variants=2, random_variants=2, attempts_per_variant=25, seed=3)


def _bump(rng, curvature=20.0, n=3000):
    """A convex bump (object surface bulging toward -z, outward normals toward -z), apex at the origin."""
    xy = rng.uniform(-0.006, 0.006, size=(n, 2))
    z = curvature * (xy**2).sum(axis=1)
    normals = np.column_stack([2 * curvature * xy, -np.ones(n)])
    return np.column_stack([xy, z]), normals / np.linalg.norm(normals, axis=1, keepdims=True)


def _in_plane_aligned(a: np.ndarray, b: np.ndarray) -> float:
    """Largest point distance after the best rotation about z (2-D Procrustes), for matched point sets."""
    h = a[:, :2].T @ b[:, :2]
    u, _, vt = np.linalg.svd(h)
    r2 = u @ vt
    if np.linalg.det(r2) < 0:
        return np.inf
    rotation = np.eye(3)
    rotation[:2, :2] = r2
    return float(np.linalg.norm(a - b @ rotation.T, axis=1).max())


def test_canonical_form_of_a_bump(rng):
    points, normals = _bump(rng)
    patch = canonicalize_patch(points, normals)
    assert np.allclose(patch.points.mean(axis=0), 0.0, atol=TOL["float"])
    # Concave direction = into the object (+z here): the centre lies below the rim.
    assert np.allclose(patch.concave_direction_source, [0, 0, 1], atol=0.02)
    radial = np.linalg.norm(patch.points[:, :2], axis=1)
    assert patch.points[radial < 0.002, 2].mean() < patch.points[radial > 0.005, 2].mean()
    assert patch.normals[:, 2].mean() < -0.9  # outward normals end up along -z


def test_canonical_form_is_invariant_to_the_patch_frame_up_to_in_plane_rotation(rng):
    points, normals = _bump(rng, curvature=15.0)
    reference = canonicalize_patch(points, normals)
    for rotation in random_rotations(rng, 10):
        T = make_transform(rotation, rng.normal(size=3))
        moved = canonicalize_patch(transform_points(T, points), rotate_vectors(T, normals))
        assert _in_plane_aligned(reference.points, moved.points) < TOL["float"]


def test_flat_patch_takes_its_sign_from_the_normals(rng):
    xy = rng.uniform(-0.006, 0.006, size=(2000, 2))
    points = np.column_stack([xy, 1e-7 * rng.normal(size=2000)])
    normals = np.tile([0.0, 0.0, 1.0], (2000, 1))  # outward +z: concave direction must be -z
    patch = canonicalize_patch(points, normals)
    assert np.allclose(patch.concave_direction_source, [0, 0, -1], atol=1e-5)
    assert patch.normals[:, 2].min() < -0.999


def test_prepare_tactile_cloud_matches_the_model_density(rng):
    pixel = 0.0634e-3
    xs, ys = np.meshgrid(np.arange(-80, 81) * pixel, np.arange(-60, 61) * pixel)
    z = 20.0 * (xs**2 + ys**2) - 0.0012
    dense = np.column_stack([xs.ravel(), ys.ravel(), z.ravel()])
    points, normals = prepare_tactile_cloud(dense, spacing_m=0.00045)
    area = (161 * pixel) * (121 * pixel)
    assert 0.7 < len(points) / (area / 0.00045**2) < 1.3
    assert (normals[:, 2] < 0).all()  # outward: toward the sensor


def test_a_sensor_view_and_a_virtual_patch_of_one_region_agree(builtin_models):
    """The same surface region, seen as a dense tactile cloud in a rolled sensor frame and as a virtual patch
    of parent points, lands in the same canonical form up to in-plane rotation."""
    model = builtin_models["figurine"]
    index = 777
    centre = model.points_object[index].astype(np.float64)
    members = model.kdtree.query_ball_point(centre, 0.006)
    virtual = canonicalize_patch(model.points_object[members].astype(np.float64), model.normals_object[members])

    # The same region as a sensor sees it: z into the object, rolled by an arbitrary angle, surface at z <= 0.
    inward = -model.aggregated_normal(centre)
    z_axis = np.array([0.0, 0.0, 1.0])
    from yoto.geometry import rotation_between

    R_object_sensor = rotation_between(z_axis, inward) @ rotation_about_axis(z_axis, 1.234)
    T_object_sensor = make_transform(R_object_sensor, centre)
    mesh_points = model.mesh_object.sample(60_000, seed=np.random.default_rng(7))
    near = mesh_points[np.linalg.norm(mesh_points - centre, axis=1) < 0.006]
    points_sensor = transform_points(np.linalg.inv(T_object_sensor), near)
    prepared, prepared_normals = prepare_tactile_cloud(points_sensor, model.point_spacing_m)
    real = canonicalize_patch(prepared, prepared_normals)

    # Compare surfaces, not point sets: the height of one over the other's nearest points, after the best
    # in-plane rotation (searched over 1 degree steps).
    from scipy.spatial import cKDTree

    best = np.inf
    for angle in np.radians(np.arange(0, 360, 1.0)):
        rotated = real.points @ rotation_about_axis(z_axis, angle).T
        distances, _ = cKDTree(virtual.points).query(rotated)
        best = min(best, np.median(distances))
    assert best < 0.6 * model.point_spacing_m


def test_variant_angles_follow_the_paper():
    angles = np.degrees(variant_angles_rad(VirtualPatchConfig()))
    assert len(angles) == 29 and angles[0] == 0.0
    assert np.allclose(angles[1:15], np.arange(12, 169, 12))
    gaps = np.abs((angles[15:, None] - np.concatenate([[0.0], angles[1:15]])[None] + 180) % 360 - 180).min(axis=1)
    assert (gaps >= 0.5).all() and ((angles[15:] >= 0) & (angles[15:] < 360)).all()


def test_generator_labels_and_determinism(builtin_models, tmp_path):
    model = builtin_models["fruit"]
    dataset = generate_virtual_patches(model, SMALL, workers=1, progress=False)
    assert len(dataset) == SMALL.num_variants * SMALL.attempts_per_variant  # a fruit has no hard spots
    sizes = np.diff(dataset.offsets)
    assert sizes.min() >= SMALL.min_points and sizes.max() <= SMALL.max_points
    for i in range(0, len(dataset), 17):
        points, normals = dataset.patch(i)
        members = dataset.indices[dataset.offsets[i] : dataset.offsets[i + 1]]
        assert np.allclose(points.mean(axis=0), 0.0, atol=TOL["float32_unit"])
        radial = np.linalg.norm(points[:, :2], axis=1)
        assert points[radial < 0.3 * radial.max(), 2].mean() < points[radial > 0.7 * radial.max(), 2].mean()
        # Labels: p is the patch point nearest the centroid, in the unrotated object frame.
        parent = model.points_object[members].astype(np.float64)
        assert np.linalg.norm(parent - dataset.p_object[i], axis=1).min() < TOL["float32"]
        assert np.linalg.norm(dataset.p_object[i] - parent.mean(axis=0)) < 0.003
        votes = np.bincount(model.point_block[members][model.point_block[members] >= 0])
        assert dataset.block[i] == np.argmax(votes)
        assert np.allclose(dataset.offset_object[i], dataset.p_object[i] - model.block_centres_object[dataset.block[i]])
    # Determinism: the same seed gives the same dataset with any number of workers; the file round-trips.
    again = generate_virtual_patches(model, SMALL, workers=2, progress=False)
    assert np.array_equal(again.indices, dataset.indices) and np.allclose(again.p_object, dataset.p_object)
    loaded = VirtualPatchDataset.load(dataset.save(tmp_path / "fruit.npz"), model)
    assert np.array_equal(loaded.block, dataset.block) and np.allclose(loaded.patch(5)[0], dataset.patch(5)[0])


def test_dataset_of_another_model_is_refused(builtin_models, tmp_path):
    from yoto.errors import InputError

    dataset = generate_virtual_patches(builtin_models["fruit"], SMALL, workers=1, progress=False)
    path = dataset.save(tmp_path / "fruit.npz")
    with pytest.raises(InputError, match="another build"):
        VirtualPatchDataset.load(path, builtin_models["figurine"])


def _height_gap(real: np.ndarray, virtual: np.ndarray) -> float:
    """Smallest, over in-plane rotations (2 deg steps), median |z| gap between the real patch's points and the
    virtual patch's surface at the same (x, y), read off its 4 nearest points in x, y."""
    from scipy.spatial import cKDTree

    tree = cKDTree(virtual[:, :2])
    best = np.inf
    for angle in np.radians(np.arange(0.0, 360.0, 2.0)):
        rotated = real @ rotation_about_axis(np.array([0.0, 0.0, 1.0]), angle).T
        _, neighbours = tree.query(rotated[:, :2], k=4)
        best = min(best, float(np.median(np.abs(rotated[:, 2] - virtual[neighbours, 2].mean(axis=1)))))
    return best


def test_a_simulated_gelsight_contact_and_a_virtual_patch_of_the_same_region_agree(builtin_models):
    """The issue's check: a GelSight press (simulator, noise-free) and the virtual patch of the parent points
    under the same footprint land in the same canonical form up to in-plane rotation."""
    from scipy.spatial import cKDTree

    from yoto.simulate.gel import ReconstructionNoise
    from yoto.simulate.press import PressConfig, PressSimulator, simulate_contact

    model = builtin_models["figurine"]
    simulator = PressSimulator(model.mesh_object, PressConfig(noise=ReconstructionNoise.none()))
    rng = np.random.default_rng(4)
    gaps, control_gaps = [], []
    while len(gaps) < 3:
        p = simulator.sample_surface(rng)[0]
        contact = simulate_contact(simulator, p, model.aggregated_normal(p), rng)
        if not contact.accepted:
            continue
        prepared, prepared_normals = prepare_tactile_cloud(contact.points_sensor, model.point_spacing_m)
        real = canonicalize_patch(prepared, prepared_normals)
        assert np.allclose(real.points.mean(axis=0), 0.0, atol=TOL["float"])
        assert real.concave_direction_source[2] > 0.9  # into the object: along the sensor's +z

        # The same surface region on the parent cloud: the parent points under the contact's footprint.
        footprint_object = transform_points(contact.press.T_object_sensor, contact.points_sensor)
        members = cKDTree(footprint_object).query(model.points_object)[0] < 0.5 * model.point_spacing_m
        virtual = canonicalize_patch(model.points_object[members].astype(np.float64), model.normals_object[members])
        gaps.append(_height_gap(real.points, virtual.points))
        # Control: the same footprint shape moved 20 mm across the surface is another region, and must not fit.
        shift = model.nearest_surface_point(
            footprint_object.mean(axis=0)
            + 0.02 * np.cross(model.aggregated_normal(contact.press.p_object), [0.0, 0.0, 1.0])
        )
        others = (
            np.linalg.norm(model.points_object - shift, axis=1)
            < np.linalg.norm(footprint_object - footprint_object.mean(axis=0), axis=1).max()
        )
        control = canonicalize_patch(model.points_object[others].astype(np.float64), model.normals_object[others])
        control_gaps.append(_height_gap(real.points, control.points))
    # Sub-0.1 mm agreement in height, and clearly better than another region of the same object.
    assert max(gaps) < 0.1e-3
    assert np.median(control_gaps) > 2 * np.median(gaps)


def test_closed_form_smallest_eigenvectors_match_eigh(rng):
    """The fast path of the PCA normals against numpy's eigh, including near-degenerate matrices."""
    from yoto.pointcloud import smallest_eigenvectors

    points = rng.normal(size=(2000, 10, 3)) * np.array([1.0, 0.5, 0.01])
    points[:50] = rng.normal(size=(50, 10, 3))  # nearly isotropic
    points[50:60, :, 2] = 0.0  # exactly planar
    centred = points - points.mean(axis=1, keepdims=True)
    covariances = np.matmul(centred.transpose(0, 2, 1), centred)
    fast = smallest_eigenvectors(covariances)
    values, vectors = np.linalg.eigh(covariances)
    reference = vectors[:, :, 0]
    well_separated = (values[:, 1] - values[:, 0]) > 1e-3 * values[:, 2]
    assert np.allclose(np.abs(np.einsum("ni,ni->n", fast, reference))[well_separated], 1.0, atol=TOL["float"])
    assert np.allclose(np.linalg.norm(fast, axis=1), 1.0)
    # Where eigenvalues nearly tie, any vector of the smallest eigenspace will do: check the Rayleigh quotient.
    rayleigh = np.einsum("ni,nij,nj->n", fast, covariances, fast)
    assert np.all(rayleigh <= values[:, 0] + 1e-6 * values[:, 2])
