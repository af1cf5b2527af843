"""Which bins of a frame `contact_samples` registers: chosen by the frame's own depths, or by the press the object at
the predicted pose makes there (`CorrectionConfig.predicted_selection`, `frame_registration.predicted_press_m`)."""

import dataclasses

import numpy as np

from yoto.tracking.config import CorrectionConfig
from yoto.tracking.frame_registration import contact_samples, predicted_press_m


class _Sphere:
    """A sphere about the origin sampled every ~0.2 mm: points, outward normals, their k-d tree."""

    def __init__(self, radius_m: float):
        from scipy.spatial import cKDTree

        count = int(4.0 * np.pi * radius_m**2 / 0.0002**2)
        k = np.arange(count) + 0.5
        polar, azimuth = np.arccos(1.0 - 2.0 * k / count), np.pi * (1.0 + 5.0**0.5) * k
        self.normals_object = np.stack(
            [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], axis=1
        )
        self.points_object = radius_m * self.normals_object
        self.kdtree = cKDTree(self.points_object)


RADIUS_M, PRESS_M = 0.015, 0.001


def _whole_pad(error_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The gel under the sphere pressed PRESS_M deep, every 0.1 mm over 12 x 10 mm (free gel read at z = 0, as a
    whole-pad cloud), plus a smooth reading error of amplitude `error_m` fixed on the pad (a 6 mm wave); and
    T_object_sensor (the sphere's centre on the sensor's z, which points into the object)."""
    x, y = (g.ravel() for g in np.meshgrid(np.arange(-0.006, 0.006, 1e-4), np.arange(-0.005, 0.005, 1e-4)))
    surface = RADIUS_M - PRESS_M - np.sqrt(np.maximum(RADIUS_M**2 - x**2 - y**2, 0.0))
    z = np.minimum(surface, 0.0) + error_m * np.sin(2.0 * np.pi * (x + 0.3 * y) / 0.006 + 0.7)
    T_object_sensor = np.eye(4)
    T_object_sensor[2, 3] = -(RADIUS_M - PRESS_M)
    return np.stack([x, y, z], axis=1), T_object_sensor


def _chosen(points: np.ndarray, config: CorrectionConfig, T_object_sensor: np.ndarray) -> set[tuple[int, int]]:
    """The bins (0.4 mm cells over the pad) whose means `contact_samples` keeps."""
    kept = contact_samples(points, config, _Sphere(RADIUS_M), T_object_sensor)  # type: ignore[arg-type]
    return {tuple(cell) for cell in np.floor(kept[:, :2] / config.voxel_m).astype(int)}


def test_the_predicted_press_is_the_sphere_s_own_depth_under_each_bin():
    """Under a 15 mm sphere pressed 1 mm the press at (x, y) is 1 mm - (r - sqrt(r^2 - x^2 - y^2)): read off the
    surface points near each place within 10 um; nan beyond the pad."""
    _, T_object_sensor = _whole_pad(0.0)
    xy = np.array([[0.0, 0.0], [0.002, 0.001], [-0.004, 0.003], [0.0055, -0.0045]])
    truth = PRESS_M - (RADIUS_M - np.sqrt(RADIUS_M**2 - np.sum(xy**2, axis=1)))
    press = predicted_press_m(_Sphere(RADIUS_M), T_object_sensor, xy, 4e-4)  # type: ignore[arg-type]
    np.testing.assert_allclose(press, truth, atol=1e-5)  # tangent planes 0.4 mm out overshoot by d^2 / 2r
    assert np.isnan(predicted_press_m(_Sphere(RADIUS_M), T_object_sensor, np.array([[0.05, 0.0]]), 4e-4)).all()  # type: ignore[arg-type]


def test_pixel_noise_moves_two_of_the_frame_s_341_chosen_bins_at_most_a_smooth_error_seven():
    """A whole-pad frame (free gel at z = 0) of the sphere pressed 1 mm, read with white pixel noise of 15 um (the
    simulator's, three draws) or with a smooth error of 20 um fixed on the pad: chosen by the frame's own depths
    (0.4 of the deepest bin's, each bin's depth averaged with its neighbours'), the noise moves at most 2 of the
    341 bins at the patch's rim, the smooth error 7: the rim a frame chooses is not its pixel noise's."""
    config = dataclasses.replace(CorrectionConfig(), points_per_contact=10_000)
    clean, T_object_sensor = _whole_pad(0.0)
    chosen = _chosen(clean, config, T_object_sensor)
    assert len(chosen) == 341
    for seed in range(3):
        noise = np.random.default_rng(seed).normal(scale=1.5e-5, size=len(clean))
        assert len(chosen ^ _chosen(clean + noise[:, None] * [0.0, 0.0, 1.0], config, T_object_sensor)) <= 2
    assert len(chosen ^ _chosen(_whole_pad(2e-5)[0], config, T_object_sensor)) == 7


def test_a_smooth_reading_error_moves_fewer_bins_chosen_by_the_predicted_press():
    """The same frame chosen by the press of the sphere at its pose (`predicted_selection`): the same patch as the
    frame's own choice without error (within 1 bin), and the smooth error of 20 um moves 4 bins, not 7 (the
    deepest read, which sets the level, moves by 0.6 x the error there)."""
    config = dataclasses.replace(CorrectionConfig(), points_per_contact=10_000)
    clean, T_object_sensor = _whole_pad(0.0)
    own = _chosen(clean, config, T_object_sensor)
    predicted_config = dataclasses.replace(config, predicted_selection=True)
    predicted = _chosen(clean, predicted_config, T_object_sensor)
    assert len(predicted ^ own) <= 1
    assert len(predicted ^ _chosen(_whole_pad(2e-5)[0], predicted_config, T_object_sensor)) <= 4
