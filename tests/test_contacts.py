"""contact_in_sensor's kept answers: the same cloud is answered from them, a changed one is computed again."""

from __future__ import annotations

import numpy as np

from yoto.contacts import _contact_in_sensor, contact_in_sensor


def _pressed_sphere(rng: np.random.Generator, centre_xy: tuple[float, float]) -> np.ndarray:
    """A tactile cloud of a 10 mm sphere pressed 0.8 mm into the gel, with 5 um of noise."""
    xy = rng.uniform(-0.004, 0.004, size=(4000, 2))
    r2 = np.sum((xy - centre_xy) ** 2, axis=1)
    xy = xy[r2 < 0.0038**2]
    r2 = r2[r2 < 0.0038**2]
    z = -(0.0008 - (0.01 - np.sqrt(0.01**2 - r2)))
    return np.column_stack([xy, np.minimum(z, 0.0) + rng.normal(0, 5e-6, len(xy))])


def test_a_kept_answer_is_the_computed_one_and_a_changed_cloud_is_recomputed():
    rng = np.random.default_rng(3)
    cloud = _pressed_sphere(rng, (0.0005, -0.0003))
    first = contact_in_sensor(cloud)
    again = contact_in_sensor(cloud.copy())  # an equal cloud (another array): the kept answer
    computed = _contact_in_sensor(cloud)
    for answer in (first, again):
        assert np.array_equal(answer[0], computed[0]) and np.array_equal(answer[1], computed[1])
    again[0][:] = 0.0  # callers get copies: changing one does not change what is kept
    assert np.array_equal(contact_in_sensor(cloud)[0], computed[0])

    cloud[:, 0] += 0.001  # changed in place: the same array, other values
    moved = contact_in_sensor(cloud)
    assert abs(moved[0][0] - computed[0][0] - 0.001) < 1e-4
    assert np.array_equal(moved[0], _contact_in_sensor(cloud)[0])

    single = cloud.astype(np.float32)  # equal values in another dtype: computed in that dtype
    assert np.array_equal(contact_in_sensor(single)[0], _contact_in_sensor(single)[0])
