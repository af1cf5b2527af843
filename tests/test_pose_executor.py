"""The pose stage on two cores (`yoto.pose.executor`): half of each batch in a helper process, bitwise as on one."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from yoto.geometry import se3_exp
from yoto.localize import make_localizer
from yoto.localize.helper import LocalizerProcess
from yoto.pose import pipeline
from yoto.pose.executor import SplitConfig, SplitExecutor, _remote_half, prepare_pose_helper
from yoto.pose.field import FieldConfig, surface_field
from yoto.pose.pipeline import PoseConfig, _pair_clouds, localize_contacts, pose_from_candidates
from yoto.pose.refine import evaluate_offsets, refine_hypotheses
from yoto.pose.search import KeyTest, key_matches, search_poses
from yoto.pose.solver import closed_form_quaternions
from yoto.registration import one_blas_thread
from yoto.simulate.scenarios import PairSimulator

COARSE = FieldConfig(cell_m=0.002)  # a field built in a second, here and in the helper


class AlwaysSplit(SplitExecutor):
    """A split executor that splits whether or not the helper finds a free core."""

    def __init__(self, *arguments):
        super().__init__(*arguments, config=SplitConfig(slow_splits=10**9))


@pytest.fixture(scope="module")
def helper():
    with LocalizerProcess(make_localizer("match")) as process:
        yield process


def _bitwise_equal(first, second) -> None:
    for name in first.__dataclass_fields__:
        a, b = getattr(first, name), getattr(second, name)
        assert a.shape == b.shape and a.tobytes() == b.tobytes(), name


def test_the_split_pose_stage_gives_one_process_s_estimate_bitwise(builtin_models, helper, monkeypatch):
    """Hypotheses, probabilities, corrections, confidence features and confidence of pairs that search (hundreds
    of seeds screened, tens refined: batches split between the two processes) are those of one process, bit for
    bit."""
    model = builtin_models["fruit"]
    calls = []
    call = LocalizerProcess.call

    def recorded(self, function, model, *arguments):  # what the helper computes: a half batch's function, by name
        calls.append((arguments[1] if function is _remote_half else function).__name__)
        return call(self, function, model, *arguments)

    monkeypatch.setattr(LocalizerProcess, "call", recorded)
    monkeypatch.setattr(pipeline, "SplitExecutor", AlwaysSplit)  # however busy the machine running the test
    prepare_pose_helper(helper, model, COARSE).result()
    localizer = make_localizer("match")
    # The family step even where the search is decisive: more batches to split.
    config = PoseConfig(search="always", suggest_next_touch=False, field_config=COARSE, family_if_decisive=True)
    for index in range(2):
        pair = PairSimulator(model).pair(seed=11, index=index).pair
        candidates, world, _ = localize_contacts(pair, model, localizer)
        calls.clear()
        one = pose_from_candidates(pair, model, candidates, world, config, "match")
        assert not calls
        two = pose_from_candidates(pair, model, candidates, world, config, "match", helper=helper)
        assert calls.count("_counted_refine") >= 5 and calls.count("evaluate_offsets") >= 1
        assert calls.count("_remote_key_matches") == 1  # the search's key test, half its rows there
        assert calls.count("_remote_closed_form") == 1  # and half of its matches' closed-form poses
        _bitwise_equal(one.hypotheses, two.hypotheses)
        assert one.T_world_object.tobytes() == two.T_world_object.tobytes()
        assert one.hypothesis_corrections.tobytes() == two.hypothesis_corrections.tobytes()
        assert one.features == two.features and one.confidence == two.confidence
        assert one.fit_rms_m == two.fit_rms_m


def test_a_split_batch_is_refined_again_whole_when_its_halves_stop_apart(builtin_models, helper):
    """The refinement stops when every pose of its batch has converged: poses that converge at once, split from
    poses that do not, would stop early in their half. The executor sees the halves ran different iteration counts
    and refines the whole batch itself; the result is the one-process refinement either way, and the scores of a
    split batch are too."""
    model = builtin_models["fruit"]
    simulated = PairSimulator(model).pair(seed=11, index=0)
    pair = simulated.pair
    config = PoseConfig(field_config=COARSE)
    field = surface_field(model, config.field_config)
    contacts = _pair_clouds(pair, model, config)
    refine = replace(
        config.refine_config, step_tolerance=3e-3
    )  # the near poses stop after 3 iterations, the far ones run 8
    truth = pair.T_world_mesh_true @ model.T_mesh_object
    rng = np.random.default_rng(3)
    near = truth @ se3_exp(rng.normal(scale=[0.002] * 3 + [0.0002] * 3, size=(8, 6)))
    far = truth @ se3_exp(rng.normal(scale=[0.1] * 3 + [0.005] * 3, size=(8, 6)))
    executor = SplitExecutor(helper, model, COARSE, SplitConfig(min_poses=4, min_scored=4, slow_splits=10**9))
    with one_blas_thread():
        for poses, redone in ((np.concatenate([near, far]), 1), (np.concatenate([far, far[::-1]]), 0)):
            before = executor.redone
            alone = refine_hypotheses(field, contacts, poses, config.calibration, refine)
            split = executor.refine(field, contacts, poses, config.calibration, refine)
            _bitwise_equal(alone, split)
            assert executor.redone - before == redone
        scores = executor.offsets(field, contacts, poses, config.calibration, refine)
        assert scores.tobytes() == evaluate_offsets(field, contacts, poses, config.calibration, refine).tobytes()
    assert executor.split == 2


def test_without_a_free_core_for_the_helper_the_stage_stays_in_this_process(builtin_models, helper):
    """Splits after which this process waited long for the helper's half (here: any wait at all) mean the helper
    finds no free core; after `slow_splits` of them the batches stay here, with the same numbers."""
    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=0).pair
    config = PoseConfig(field_config=COARSE)
    field = surface_field(model, config.field_config)
    contacts = _pair_clouds(pair, model, config)
    truth = pair.T_world_mesh_true @ model.T_mesh_object
    poses = truth @ se3_exp(np.random.default_rng(4).normal(scale=[0.05] * 3 + [0.003] * 3, size=(20, 6)))
    executor = SplitExecutor(helper, model, COARSE, SplitConfig(max_wait_share=-1.0, slow_splits=2))
    with one_blas_thread():
        alone = refine_hypotheses(field, contacts, poses, config.calibration, config.refine_config)
        for _ in range(3):
            _bitwise_equal(alone, executor.refine(field, contacts, poses, config.calibration, config.refine_config))
    assert executor.split == 2 and executor.slow == 2


def test_the_search_s_key_test_split_between_two_processes_finds_the_same_pairs(builtin_models, helper, monkeypatch):
    """The search's location pairs, their rows cut between two chunks and the second part tested in the helper,
    are the same pairs in the same order with the same mismatches as all rows tested at once; a test too small to
    split stays here."""
    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=1).pair
    localizer = make_localizer("match")
    candidates, world, _ = localize_contacts(pair, model, localizer)
    config = PoseConfig()
    shapes = pipeline._contact_shapes(pair, world, config)
    tests: list[KeyTest] = []

    def recorded(test: KeyTest):
        tests.append(test)
        return key_matches(test)

    search_poses(model, world, shapes, candidates, config.search_config, matcher=recorded)
    (test,) = tests
    assert test.rows > 2 * test.chunk  # several chunks: the cut falls between two of them
    calls = []
    call = LocalizerProcess.call

    def counted(self, function, model, *arguments):
        calls.append(function.__name__)
        return call(self, function, model, *arguments)

    monkeypatch.setattr(LocalizerProcess, "call", counted)
    executor = AlwaysSplit(helper, model, COARSE)
    with one_blas_thread():
        alone = key_matches(test)
        split = executor.key_matches(test)
        assert calls == ["_remote_key_matches"]
        one_chunk = replace(test, left_rows=test.left_rows[: test.chunk], low_rows=test.low_rows[: test.chunk])
        assert len(executor.key_matches(one_chunk)[0]) > 0 and calls == ["_remote_key_matches"]  # not split
    assert len(alone[0]) > 1000
    for a, b in zip(alone, split):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()


def test_the_search_s_closed_form_poses_split_between_two_processes_are_the_same(builtin_models, helper, monkeypatch):
    """The closed-form poses of a search's matches, their rows cut in two and the second part posed in the helper,
    are those of all rows at once, bit for bit (each row's arithmetic is its own); too few matches stay here."""
    model = builtin_models["fruit"]
    pair = PairSimulator(model).pair(seed=11, index=1).pair
    candidates, world, _ = localize_contacts(pair, model, make_localizer("match"))
    config = PoseConfig()
    shapes = pipeline._contact_shapes(pair, world, config)
    posed = []

    def recorded(*arguments):
        posed.append(arguments)
        return closed_form_quaternions(*arguments)

    search_poses(model, world, shapes, candidates, config.search_config, solver=recorded)
    (arguments,) = posed
    assert len(arguments[0]) > 4000  # thousands of matches: split
    calls = []
    call = LocalizerProcess.call

    def counted(self, function, model, *rest):
        calls.append(function.__name__)
        return call(self, function, model, *rest)

    monkeypatch.setattr(LocalizerProcess, "call", counted)
    executor = AlwaysSplit(helper, model, COARSE)
    few = tuple(rows[:100] for rows in arguments[:4]) + arguments[4:]
    with one_blas_thread():
        alone = closed_form_quaternions(*arguments)
        split = executor.closed_form(*arguments)
        assert calls == ["_remote_closed_form"]
        assert executor.closed_form(*few)[0].tobytes() == closed_form_quaternions(*few)[0].tobytes()
        assert calls == ["_remote_closed_form"]  # not split
    for a, b in zip(alone, split):
        assert a.shape == b.shape and a.tobytes() == b.tobytes()
