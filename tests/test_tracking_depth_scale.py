"""A reconstruction's depth scale error taken out of a contact's shape before the closed loop registers it
(`frame_registration.without_depth_scale`, `CorrectionConfig.image_depth_scale`)."""

import dataclasses

import numpy as np
import pytest

from yoto.geometry import pose_from_twist, transform_points
from yoto.registration import plane_distances
from yoto.tracking.config import CorrectionConfig
from yoto.tracking.frame_registration import without_depth_scale


class _Sphere:
    """A sphere about the origin sampled every ~0.3 mm: points, outward normals, their k-d tree."""

    def __init__(self, radius_m: float):
        from scipy.spatial import cKDTree

        count = int(4.0 * np.pi * radius_m**2 / 0.0003**2)
        k = np.arange(count) + 0.5
        polar, azimuth = np.arccos(1.0 - 2.0 * k / count), np.pi * (1.0 + 5.0**0.5) * k
        self.normals_object = np.stack(
            [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1
        )
        self.points_object = radius_m * self.normals_object
        self.kdtree = cKDTree(self.points_object)


def _pressed(radius_m: float, press_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The gel's pressed points (sensor frame, the rest surface z = 0, pressed points below it) under a sphere
    pressed `press_m` deep, every 0.2 mm, those at least 40% as deep as the deepest (what `contact_samples` keeps);
    and T_object_sensor (the sphere's centre on the sensor's z, which points into the object)."""
    x, y = (grid.ravel() for grid in np.meshgrid(np.arange(-0.004, 0.004, 0.0002), np.arange(-0.004, 0.004, 0.0002)))
    z = radius_m - press_m - np.sqrt(radius_m**2 - x**2 - y**2)
    keep = z <= 0.4 * -press_m
    T_object_sensor = np.eye(4)
    T_object_sensor[2, 3] = -(radius_m - press_m)
    return np.stack([x[keep], y[keep], z[keep]], axis=1), T_object_sensor


def _share_read(read: np.ndarray, reshaped: np.ndarray) -> float:
    """The share by which a frame read its depths about their mean too deep (negative: too shallow), as
    `without_depth_scale` took it out: from the scale it put on them."""
    depth = read[:, 2] - read[:, 2].mean()
    scale = np.dot(reshaped[:, 2] - reshaped[:, 2].mean(), depth) / np.dot(depth, depth)
    return float(1.0 / scale - 1.0)


def test_a_contact_read_15_percent_shallow_is_reshaped_onto_the_surface_whatever_the_prediction_is_off_by():
    """A sphere (r 15 mm) pressed 1 mm, the frame reading its depths 15% shallow, its points' errors taken as
    independent (`bias_points` all of them): the share comes back as -0.15 and the points reshaped about their
    mean depth lie on the surface up to that mean (the press, left to the registration: their spread about the
    surface 1.3 um from 26), also from a prediction 0.2 mm and 1 deg off (the rigid motion estimated beside the
    share); a frame read right is left as it is."""
    radius = 0.015
    sphere = _Sphere(radius)
    true_points, T_object_sensor = _pressed(radius, 0.001)
    read = true_points * [1.0, 1.0, 0.85]
    config = dataclasses.replace(CorrectionConfig(), bias_points=float(len(read)))

    def spread_on_surface(points_sensor: np.ndarray) -> float:
        distance, matched, _, _ = plane_distances(sphere, transform_points(T_object_sensor, points_sensor), 0.002)
        assert matched.all()
        return float(np.std(distance))

    assert spread_on_surface(read) > 2e-5 > 1e-6 > spread_on_surface(true_points)
    for off in (np.zeros(6), np.array([0.0, np.radians(1.0), 0.0, 0.0002, 0.0, 0.0])):
        predicted = pose_from_twist(off) @ T_object_sensor
        reshaped = without_depth_scale(sphere, read, predicted, config.image_depth_scale, config)
        assert _share_read(read, reshaped) == pytest.approx(-0.15, abs=0.01)
        assert spread_on_surface(reshaped) < 3e-6
        np.testing.assert_allclose(reshaped[:, :2], read[:, :2])
        assert np.mean(reshaped[:, 2]) == pytest.approx(np.mean(read[:, 2]), abs=1e-9)
    as_read = without_depth_scale(sphere, true_points, T_object_sensor, config.image_depth_scale, config)
    assert _share_read(true_points, as_read) == pytest.approx(0.0, abs=0.003)
    np.testing.assert_allclose(as_read, true_points, atol=3e-6)


def test_the_share_is_shrunk_where_the_patch_s_shape_tells_it_as_a_smooth_error_would():
    """With the default 3 points of shared error (`bias_points`), 15% shallow comes back as 13% on a 15 mm sphere
    pressed 1 mm (depths 0.17 mm about their mean) and as 7% on a 60 mm one (0.06 mm, as flat as a smooth error
    of the gel makes it): what a shallow patch's shape tells of its scale, a pad's smooth error could tell too."""
    config = CorrectionConfig()
    shares = {}
    for radius in (0.015, 0.06):
        points, T_object_sensor = _pressed(radius, 0.001)
        read = points * [1.0, 1.0, 0.85]
        reshaped = without_depth_scale(_Sphere(radius), read, T_object_sensor, config.image_depth_scale, config)
        shares[radius] = _share_read(read, reshaped)
    assert shares[0.015] == pytest.approx(-0.131, abs=0.005)
    assert shares[0.06] == pytest.approx(-0.067, abs=0.005)


def test_the_closed_loop_reshapes_the_frames_it_reads_from_images_and_leaves_clouds_as_given(
    builtin_models, monkeypatch
):
    """The same simulated frames tracked as clouds given as clouds (`from_images` False: untouched, the poses as
    with the step off) and as frames from images (each registered frame reshaped, the poses move by up to 0.11 mm)."""
    pytest.importorskip("open3d")
    from test_tracking_closed_loop import SHORT

    import yoto.tracking.correction as correction
    from yoto.simulate.trajectory import TrajectorySimulator
    from yoto.tracking.bench import tactile_streams
    from yoto.tracking.touch import touch_from_pair
    from yoto.tracking.track import TrackConfig, track

    model = builtin_models["fruit"]
    trajectory = TrajectorySimulator(model, SHORT).trajectory(3, 1)
    touch = touch_from_pair(trajectory.touch.pair, trajectory.touch.T_world_object, trajectory.touch_time_s)
    calls = []

    def counted(*args, **kwargs):
        calls.append(1)
        return without_depth_scale(*args, **kwargs)

    monkeypatch.setattr(correction, "without_depth_scale", counted)
    clouds = tactile_streams(trajectory)
    off = TrackConfig(correction=dataclasses.replace(CorrectionConfig(), image_depth_scale=0.0))
    as_clouds = track(touch, trajectory.streams, model, clouds).T_world_object
    assert not calls
    np.testing.assert_array_equal(as_clouds, track(touch, trajectory.streams, model, clouds, off).T_world_object)
    images = {side: dataclasses.replace(stream, from_images=True) for side, stream in clouds.items()}
    result = track(touch, trajectory.streams, model, images)
    assert len(calls) >= result.correction_summary()["frames_used"] > 0
    assert np.abs(result.T_world_object[:, :3, 3] - as_clouds[:, :3, 3]).max() > 5e-5
