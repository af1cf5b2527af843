"""Errors cross process boundaries (the pose stage's helper process, benchmark workers) pickled."""

import pickle

from yoto.errors import DegenerateGeometryError, InputError, MissingDependencyError, NoContactError


def test_every_error_survives_the_trip_back_from_a_worker_process():
    errors = [
        InputError("missing key 'left'", "pairs/pair.json"),
        NoContactError("no contact", "left.png"),
        DegenerateGeometryError("a flat patch"),
        MissingDependencyError("open3d", "geometry", "ray casting on the object mesh"),
    ]
    for error in errors:
        back = pickle.loads(pickle.dumps(error))
        assert type(back) is type(error) and str(back) == str(error)
        assert getattr(back, "path", None) == getattr(error, "path", None)
    assert "pip install 'yoto[geometry]'" in str(errors[-1])
