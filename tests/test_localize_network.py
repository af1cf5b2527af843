"""The network localizer: candidates, beliefs, block-feature cache, errors for missing or foreign checkpoints."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from test_training import cut_contact, tiny_run, write_cut_pairs  # noqa: E402

from yoto.contacts import contact_in_sensor  # noqa: E402
from yoto.errors import InputError  # noqa: E402
from yoto.geometry import rotation_angle_rad  # noqa: E402
from yoto.localize import make_localizer  # noqa: E402
from yoto.localize.network import (  # noqa: E402
    NetworkLocalizer,
    UnknownObjectWarning,
    default_checkpoint_path,
    measure_latency,
)
from yoto.network.candidates import Candidate, candidates_of, fit_temperature, softmax  # noqa: E402
from yoto.network.checkpoint import LocalizerCheckpoint, load_torch, save_torch_atomic  # noqa: E402
from yoto.network.presets import network_config_from_dict  # noqa: E402
from yoto.objects.build import load_object_model  # noqa: E402
from yoto.workspace import object_model_path  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Small tensors gain nothing from threads, and on a shared machine extra threads only spin."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def localizer(builtin_models, tmp_path_factory):
    return make_localizer("yoto", str(tiny_run(builtin_models, tmp_path_factory)))


def test_localizer_returns_ranked_candidates_with_beliefs(localizer, builtin_models, rng):
    model = builtin_models["fruit"]
    points, _, p_true = cut_contact(model, int(rng.integers(len(model.points_object))), rng)
    candidates = localizer.localize(points, model)
    assert isinstance(localizer, NetworkLocalizer) and localizer.name == "yoto" and not localizer.needs_ground_truth
    assert 1 <= len(candidates) <= localizer.hypotheses
    # The paper's answer first, then the other hypotheses by score.
    assert candidates[0].details["hypothesis"] == 0
    rest = [c.score for c in candidates[1:]]
    assert rest == sorted(rest, reverse=True)
    probabilities = np.array([c.probability for c in candidates])
    assert ((probabilities >= 0) & (probabilities <= 1)).all() and probabilities.sum() == pytest.approx(1.0)
    blocks = [c.block for c in candidates]
    assert len(set(blocks)) == len(blocks)
    for candidate in candidates:
        # On the model's scale, unit kNN-aggregated normals, scores = coarse + confidence.
        assert np.abs(candidate.p_object).max() < model.mesh_scale_m
        np.testing.assert_allclose(candidate.n_object, model.aggregated_normal(candidate.p_object, 20))
        details = candidate.details
        assert candidate.score == pytest.approx(details["coarse_score"] + details["fine_confidence"], abs=1e-3)
    json.dumps([c.details for c in candidates])  # JSON-serialisable
    coarse = candidates[0].details["coarse_top_logits"]
    assert coarse == sorted(coarse, reverse=True) and len(coarse) == localizer.config.candidates


def test_block_features_are_computed_once_per_model(localizer, builtin_models, rng):
    model = builtin_models["fruit"]
    first = localizer.prepare_object(model)
    assert localizer.prepare_object(model) is first
    points, _, _ = cut_contact(model, 123, rng)
    batch = localizer.localize_many([points, points], model)
    single = localizer.localize(points, model)
    np.testing.assert_allclose(batch[0][0].p_object, single[0].p_object, atol=1e-6)
    latency = measure_latency(localizer, [points] * 3, model)
    assert latency["calls"] == 3 and 0 < latency["median_ms"] <= latency["p90_ms"] * 1.0001


def test_other_objects_work_but_warn(localizer, builtin_models, rng):
    figurine = builtin_models["figurine"]
    points, _, _ = cut_contact(figurine, 500, rng)
    with pytest.warns(UnknownObjectWarning, match="not one this localizer was trained on"):
        candidates = localizer.localize(points, figurine)
    assert candidates and candidates[0].details["trained_object"] is False


def test_missing_checkpoints_give_clear_errors(tmp_path, monkeypatch):
    with pytest.raises(InputError, match="localizer checkpoint not found"):
        NetworkLocalizer.from_checkpoint(tmp_path / "nope.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="not a readable"):
        NetworkLocalizer.from_checkpoint(tmp_path / "junk.pt")
    monkeypatch.setattr("yoto.localize.network.default_checkpoint_path", lambda: tmp_path / "default.pt")
    with pytest.raises(InputError, match="yoto train"):
        NetworkLocalizer.from_checkpoint(None)


def test_foreign_old_and_damaged_checkpoints_are_refused_by_name(localizer, tmp_path):
    payload = load_torch(localizer.source, "localizer checkpoint")
    cases = {
        "foreign.pt": ({**payload, "format": "someone-else"}, "not a YOTO localizer checkpoint"),
        "old.pt": ({**payload, "format_version": 0}, "format version 0 is not supported"),
        "damaged.pt": ({k: v for k, v in payload.items() if k != "state_dict"}, "incomplete or damaged"),
        "list.pt": ([1, 2], "not a YOTO localizer checkpoint"),
    }
    for name, (content, message) in cases.items():
        save_torch_atomic(tmp_path / name, content)
        with pytest.raises(InputError, match=message) as error:
            NetworkLocalizer.from_checkpoint(tmp_path / name)
        assert error.value.path == tmp_path / name


def test_the_shipped_weights_read_unchanged(tmp_path):
    path = default_checkpoint_path()
    if not path.is_file():
        pytest.skip("this copy of YOTO has no shipped weights")
    on_disk = load_torch(path, "localizer checkpoint")
    checkpoint = LocalizerCheckpoint.load(path)
    assert checkpoint.to_payload().keys() == on_disk.keys()
    for key, value in checkpoint.to_payload().items():
        if key == "state_dict":
            assert value.keys() == on_disk[key].keys()
            assert all(torch.equal(value[name], on_disk[key][name]) for name in value)
        elif key == "network_config":  # files written before configs named their kind hold a point network
            assert value == {"kind": "points", **on_disk[key]}, key
        else:
            assert value == on_disk[key], key
    localizer = make_localizer("yoto")
    assert sorted(o.name for o in localizer.trained_objects) == sorted(o.name for o in checkpoint.objects)
    fruit = load_object_model("fruit", workspace=tmp_path)  # the built-in fruit as `yoto demo` builds it
    with warnings.catch_warnings():  # ... is one the weights learnt
        warnings.simplefilter("error")
        assert localizer.prepare_object(fruit).trained
    card = json.loads(path.with_suffix(".json").read_text())
    assert network_config_from_dict(card["network_config"]) == checkpoint.network_config
    assert card["command"].startswith("yoto train")


def test_candidates_merge_close_hypotheses_and_sum_beliefs():
    ranking = {
        "best": np.array([[0, 0, 0]]),
        "pools": np.array([[[4], [7], [9]]]),
        "positions": np.array([[[[0.0, 0, 0]], [[0.002, 0, 0]], [[0.05, 0, 0]]]]),
        "scores": np.array([[[1.0], [3.0], [2.0]]]),
        "confidence": np.zeros((1, 3, 1)),
        "logits": np.zeros((1, 10)),
    }
    found = candidates_of(ranking, 0, temperature=1.0, merge_radius_m=0.005)
    beliefs = softmax(np.array([1.0, 3.0, 2.0]), 1.0)
    # Hypothesis 0 (the paper's answer) first; block 7 lies 2 mm from it and merges into it.
    assert [c.block for c in found] == [4, 9]
    assert found[0].probability == pytest.approx(beliefs[0] + beliefs[1])
    assert found[1].probability == pytest.approx(beliefs[2])
    by_score = candidates_of(ranking, 0, temperature=1.0, merge_radius_m=0.0, paper_first=False)
    assert [c.block for c in by_score] == [7, 9, 4]
    assert isinstance(by_score[0], Candidate)


def test_fitted_temperature_follows_how_often_the_top_score_is_right():
    scores = [np.array([2.0, 0.0])] * 10
    confident = fit_temperature(scores, [np.array([True, False])] * 10)
    unsure = fit_temperature(scores, [np.array([True, False])] * 6 + [np.array([False, True])] * 4)
    assert confident < 0.5 < unsure  # always right: sharpen; right 60%: soften
    assert softmax(np.array([2.0, 0.0]), unsure)[0] == pytest.approx(0.6, abs=0.05)


def test_localize_cli_writes_the_contact_in_both_frames(localizer, builtin_models, tmp_path, rng):
    from yoto.cli import main
    from yoto.io import write_ply_points
    from yoto.workspace import object_model_path

    model = builtin_models["fruit"]
    model.save(object_model_path("fruit", tmp_path))
    points, _, _ = cut_contact(model, 777, rng)
    cloud = write_ply_points(tmp_path / "contact.ply", points)
    out = tmp_path / "result.json"
    code = main(
        [
            "localize",
            str(cloud),
            "--object",
            "fruit",
            "--workspace",
            str(tmp_path),
            "--method",
            "yoto",
            "--checkpoint",
            str(localizer.source),
            "--out",
            str(out),
        ]
    )
    assert code == 0
    result = json.loads(out.read_text())
    contact = result["contact"]
    p_mesh = model.T_mesh_object[:3, :3] @ np.array(contact["p_object"]) + model.T_mesh_object[:3, 3]
    np.testing.assert_allclose(contact["p_mesh"], p_mesh, atol=1e-9)
    assert 0 <= contact["probability"] <= 1 and result["candidates"][0] == contact


def test_pose_stage_uses_the_network_localizer(localizer, builtin_models, tmp_path, rng):
    from yoto.contacts import read_contact_pair
    from yoto.pose.pipeline import estimate_pose

    model = builtin_models["fruit"]
    (path,) = write_cut_pairs(model, tmp_path, 1, rng)
    estimate = estimate_pose(read_contact_pair(path), model, localizer)
    assert estimate.method == "yoto" and 0.0 <= estimate.confidence <= 1.0
    assert estimate.latency_ms["localize_left"] > 0


# ---------------------------------------------------------------------------------------- the `cpu` preset
@pytest.fixture(scope="module")
def descriptor_checkpoint(builtin_models, tmp_path_factory):
    from test_training_descriptor import tiny_descriptor_run

    workspace = tmp_path_factory.mktemp("ws_descriptor_localizer")
    builtin_models["fruit"].save(object_model_path("fruit", workspace))
    return tiny_descriptor_run(workspace)


@pytest.fixture(scope="module")
def fruit_pairs(builtin_models):
    from yoto.simulate.scenarios import PairSimulator

    return [PairSimulator(builtin_models["fruit"]).pair(11, i) for i in range(3)]


def test_load_localizer_picks_the_checkpoints_network(descriptor_checkpoint, localizer):
    from yoto.localize.descriptor import DescriptorLocalizer
    from yoto.localize.network import load_localizer

    assert isinstance(make_localizer("yoto", str(descriptor_checkpoint)), DescriptorLocalizer)
    assert isinstance(load_localizer(localizer.source), NetworkLocalizer)
    with pytest.raises(InputError, match="anchor-descriptor network"):
        NetworkLocalizer.from_checkpoint(descriptor_checkpoint)


def test_the_fine_stage_finds_contacts_among_all_anchors(descriptor_checkpoint, builtin_models, fruit_pairs):
    """With every anchor shortlisted the network has no say: the roll search, the poses it proposes and ICP must
    find simulated contacts on the bumpy fruit by themselves (as the matched filter does, tests/test_match.py)."""
    from yoto.localize.descriptor import DescriptorLocalizerConfig
    from yoto.localize.network import load_localizer

    model = builtin_models["fruit"]
    localizer = load_localizer(descriptor_checkpoint, config=DescriptorLocalizerConfig(shortlist=100_000))
    hits = 0
    for simulated in fruit_pairs:
        for side in ("left", "right"):
            candidates = localizer.localize(simulated.pair.contact(side).points_sensor, model)
            probabilities = np.array([c.probability for c in candidates])
            assert (probabilities >= 0).all() and probabilities.sum() <= 1.0 + 1e-9
            residuals = [c.details["residual_mm"] for c in candidates]
            assert residuals == sorted(residuals)
            places = np.array([c.p_object for c in candidates])
            gaps = np.linalg.norm(places[:, None] - places[None], axis=2) + np.eye(len(places))
            assert gaps.min() >= localizer.config.belief.dedup_radius_m
            json.dumps([c.details for c in candidates])
            if np.linalg.norm(candidates[0].p_object - simulated.p_object_true[side]) < 0.0025:
                hits += 1
                # The sensor pose behind the answer is the simulator's: the press axis to a few degrees, the roll as
                # well as the contact's shape allows, the contact's centre to a couple of millimetres (a slide along the
                # surface is weakly constrained).
                T_true = simulated.contacts[side].press.T_object_sensor
                T_found = np.array(candidates[0].details["T_object_sensor"])
                assert np.degrees(np.arccos(min(T_found[:3, 2] @ T_true[:3, 2], 1.0))) < 3.0
                assert np.degrees(rotation_angle_rad(T_found, T_true)) < 15.0
                centre_sensor, _ = contact_in_sensor(simulated.pair.contact(side).points_sensor)
                centres = [T[:3, :3] @ centre_sensor + T[:3, 3] for T in (T_found, T_true)]
                assert np.linalg.norm(centres[0] - centres[1]) < 0.002
                assert candidates[0].details["residual_mm"] < 0.1
    assert hits >= 5


def test_the_ablation_switches_skip_stages(descriptor_checkpoint, builtin_models, fruit_pairs):
    from yoto.localize.descriptor import DescriptorLocalizerConfig
    from yoto.localize.network import load_localizer

    model = builtin_models["fruit"]
    simulated = fruit_pairs[0]
    points = simulated.pair.contact("left").points_sensor
    coarse = load_localizer(descriptor_checkpoint, config=DescriptorLocalizerConfig(fine_stage=False))
    found = coarse.localize(points, model)
    anchors = coarse.prepare_object(model).anchors
    scores = [c.details["descriptor_score"] for c in found]
    assert scores == sorted(scores, reverse=True) and sum(c.probability for c in found) == pytest.approx(1.0)
    for candidate in found:  # the anchors themselves
        np.testing.assert_array_equal(candidate.p_object, anchors.points_object[candidate.details["anchor"]])
    fits = load_localizer(descriptor_checkpoint, config=DescriptorLocalizerConfig(refine=False, shortlist=100_000))
    unrefined = fits.localize(points, model)
    assert [c.details["residual_mm"] for c in unrefined] == [c.details["fit_rms_mm"] for c in unrefined]
    assert min(np.linalg.norm(c.p_object - simulated.p_object_true["left"]) for c in unrefined) < 0.003


def test_objects_the_descriptor_network_did_not_see_work_but_warn(descriptor_checkpoint, builtin_models, rng):
    from yoto.localize.network import load_localizer

    localizer = load_localizer(descriptor_checkpoint)
    figurine = builtin_models["figurine"]
    points, _, _ = cut_contact(figurine, 500, rng)
    with pytest.warns(UnknownObjectWarning, match="not one this localizer was trained on"):
        candidates = localizer.localize(points, figurine)
    assert candidates and not candidates[0].details["trained_object"]


def test_a_rebuild_of_a_trained_object_counts_as_trained_where_its_anchors_match():
    from types import SimpleNamespace

    from yoto.localize.network import is_trained_object
    from yoto.network.checkpoint import TrainedObject

    trained = [TrainedObject("fruit", "ce81d0dd236c624b", 6544)]
    rebuilt = SimpleNamespace(name="fruit", fingerprint="827de8f5bca16728")  # the last bits of its points moved
    assert is_trained_object(SimpleNamespace(name="x", fingerprint="ce81d0dd236c624b"), trained, "", None)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert is_trained_object(rebuilt, trained, "", anchors=6544)
    with pytest.warns(UnknownObjectWarning, match="a model of that name but another build"):
        assert not is_trained_object(rebuilt, trained, "", anchors=6545)  # another surface
    with pytest.warns(UnknownObjectWarning):
        assert not is_trained_object(rebuilt, trained, "", anchors=None)  # no anchors to compare: the build decides
