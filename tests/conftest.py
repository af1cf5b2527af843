"""Shared test helpers: one seeded RNG factory, one tolerance table, the shared-data location."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

# Where `../shared/data` lives relative to the repository (CI has it there; a user's clone may not).
SHARED_DATA = Path(os.environ.get("YOTO_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))

# Tolerances, in one place. Float-precision recoveries are compared with FLOAT; metric tolerances carry units.
TOL = {
    "float": 1e-9,  # float64 results of exact math (sums, products, solves of well-conditioned systems)
    "float_round_trip": 1e-12,  # exp/log, quaternion and orthogonality round trips (a few ulps of values near 1)
    "float32": 1e-5,  # values that passed through float32 storage, metres
    "float32_unit": 1e-6,  # unit vectors that passed through float32 storage
    "ply_text_m": 1e-8,  # coordinates written to and read back from PLY files
    "tum_text": 1e-8,  # pose entries written to and read back from TUM files (9 decimals)
    "arccos_rad": 1e-6,  # angles read off arccos near 1 (its derivative diverges there)
    "pose_exact_m": 1e-9,  # noise-free pose recovery, translation
    "pose_exact_rad": 1e-9,  # noise-free pose recovery, rotation
}


@pytest.fixture
def rng() -> np.random.Generator:
    """The one seeded generator tests draw from (same seed every test: failures reproduce)."""
    return np.random.default_rng(12345)


def shared_data(*parts: str) -> Path:
    """Path under ../shared/data, or skip the test with a reason when it is absent."""
    path = SHARED_DATA.joinpath(*parts)
    if not path.exists():
        pytest.skip(f"needs the shared data at {path} (not part of a user's clone)")
    return path


@pytest.fixture(scope="session")
def builtin_models(tmp_path_factory):
    """Object models of the built-in objects, built once per test session at a reduced cloud size."""
    from yoto.objects.builtin import builtin_mesh
    from yoto.objects.model import ObjectModelConfig, build_object_model

    config = ObjectModelConfig(num_points=40_000)
    return {name: build_object_model(builtin_mesh(name), name, config) for name in ("tool", "fruit", "figurine")}


@pytest.fixture(scope="session")
def fruit_contacts(builtin_models):
    """Six simulated GelSight contacts on the bumpy fruit (seed 11, pairs 0-2): (tactile points, true contact point,
    true T_object_sensor) each, with the fruit's model."""
    from yoto.simulate.scenarios import PairSimulator

    model = builtin_models["fruit"]
    simulator = PairSimulator(model)
    contacts = []
    for index in range(3):
        simulated = simulator.pair(seed=11, index=index)
        for side, contact in simulated.contacts.items():
            contacts.append(
                (
                    simulated.pair.contact(side).points_sensor,
                    simulated.p_object_true[side],
                    contact.press.T_object_sensor,
                )
            )
    return model, contacts
