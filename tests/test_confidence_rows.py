"""The calibration rows the confidence is fitted and studied on."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from conftest import TOL

from yoto.evaluation.calibrate import hypothesis_rows
from yoto.geometry import make_transform, rotation_about_axis
from yoto.objects.symmetry import Symmetry
from yoto.pose.hypotheses import Hypotheses

DEG_TOL = float(np.degrees(TOL["arccos_rad"]))  # rotation distances are read off arccos


def test_hypothesis_rows_measure_each_hypothesis_from_the_first_and_the_truth():
    T_true = make_transform(np.eye(3), [0.4, 0.1, 0.2])
    near = T_true @ make_transform(rotation_about_axis(np.array([1.0, 0.0, 0.0]), np.radians(3.0)), [0.002, 0, 0])
    turned = T_true @ make_transform(rotation_about_axis(np.array([0.0, 1.0, 0.0]), np.radians(20.0)), [0, 0, 0])
    slid = T_true @ make_transform(np.eye(3), [0.0, 0.0, 0.012])
    poses = np.array([near, turned, slid])
    hypotheses = Hypotheses(poses, np.array([0.6, 0.3, 0.1]), np.array([0.0, -1.0, -2.0]), np.arange(3), np.ones(3))
    model = SimpleNamespace(symmetry=Symmetry(), T_mesh_object=np.eye(4))
    rows = np.array(hypothesis_rows(model, SimpleNamespace(hypotheses=hypotheses), T_true))
    assert rows.shape == (3, 5)
    assert np.allclose(rows[:, 0], [0.6, 0.3, 0.1]) and np.allclose(rows[:, 1], [0.0, -1.0, -2.0])
    assert rows[0, 2] == pytest.approx(0.0, abs=TOL["float"]) and rows[0, 3] == pytest.approx(0.0, abs=DEG_TOL)
    assert rows[2, 2] == pytest.approx(np.linalg.norm(slid[:3, 3] - near[:3, 3]) * 1000.0, abs=TOL["float"])
    assert rows[2, 3] == pytest.approx(3.0, abs=DEG_TOL)  # the slid pose keeps the truth's rotation
    assert rows[:, 4].tolist() == [1.0, 0.0, 0.0]  # 2 mm / 3 deg right; 20 deg and 12 mm wrong


def test_rows_key_changes_with_the_localizer_and_pose_settings(monkeypatch):
    """Cached rows are reused only by the same localizer and pose-stage settings and the same code: a changed default
    (fewer ICP candidates kept), pose config or commit gives a new key; the same settings in a new instance give the
    same key."""
    from dataclasses import replace

    import yoto.evaluation.calibrate as calibrate
    from yoto.evaluation.calibrate import CalibrationConfig, rows_key
    from yoto.localize.match.config import MatchConfig
    from yoto.localize.scaled_match import ScaledMatchLocalizer
    from yoto.pose.pipeline import PoseConfig

    config, pose = CalibrationConfig(), PoseConfig()
    key = rows_key(config, "abc", ScaledMatchLocalizer(), pose)
    assert key == rows_key(config, "abc", ScaledMatchLocalizer(MatchConfig()), PoseConfig())
    cut = ScaledMatchLocalizer(replace(MatchConfig(), icp_keep=7, polish_iterations=1))
    others = {
        rows_key(config, "abc", cut, pose),
        rows_key(config, "abc", ScaledMatchLocalizer(), replace(pose, search="always")),
        rows_key(config, "abd", ScaledMatchLocalizer(), pose),
        rows_key(replace(config, seed=12), "abc", ScaledMatchLocalizer(), pose),
    }
    assert key not in others and len(others) == 4
    monkeypatch.setattr(calibrate, "git_commit", lambda: "0123abc")  # another commit of the same version
    assert rows_key(config, "abc", ScaledMatchLocalizer(), pose) != key


def test_fit_only_settings_reuse_rows_and_the_fit_reads_its_features_by_name():
    """The ridge penalty and the features a model uses do not change the rows (all features are kept): the same key;
    a fit on some of them reads their columns by name, in the model's order."""
    from dataclasses import replace

    from yoto.evaluation.calibrate import CalibrationConfig, Rows, feature_matrix, rows_key
    from yoto.localize.scaled_match import ScaledMatchLocalizer
    from yoto.pose.confidence import FEATURES
    from yoto.pose.pipeline import PoseConfig

    config = CalibrationConfig()
    key = rows_key(config, "abc", ScaledMatchLocalizer(), PoseConfig())
    fit_only = replace(config, l2=0.5, features=("spread", "belief"))
    assert rows_key(fit_only, "abc", ScaledMatchLocalizer(), PoseConfig()) == key
    values = np.arange(2 * len(FEATURES), dtype=float).reshape(2, len(FEATURES))
    rows = [Rows("a", values[:1].tolist(), [True], [0.5]), Rows("b", values[1:].tolist(), [False], [0.5])]
    picked = feature_matrix(rows, ("spread", "belief"))
    assert picked.tolist() == [[values[r, FEATURES.index(n)] for n in ("spread", "belief")] for r in range(2)]
