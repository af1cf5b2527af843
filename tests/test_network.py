"""The localization network: encoder fast paths against slow references, invariances, heads and shapes."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from scipy.spatial import cKDTree  # noqa: E402

from yoto.network.encoder import (  # noqa: E402
    MultiScaleEdge,
    PointEncoder,
    knn_indices,
    neighbour_max,
    reference_edge_features,
)
from yoto.network.inputs import block_neighbours  # noqa: E402
from yoto.network.model import ContactLocalizationNet  # noqa: E402
from yoto.network.presets import PRESETS, NetworkConfig  # noqa: E402

TINY = NetworkConfig(
    points_per_patch=48,
    points_per_block=64,
    knn_scales=(4, 8, 16),
    point_dim=16,
    edge_dim=8,
    fusion_dim=16,
    prepool_dim=24,
    feature_dim=12,
    candidates=4,
    fine_dims=(16, 8),
)


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Small tensors gain nothing from threads, and on a shared machine extra threads only spin."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def _cloud(rng, batch, count):
    points = torch.from_numpy(rng.normal(scale=0.004, size=(batch, count, 3)).astype(np.float32))
    normals = torch.nn.functional.normalize(
        torch.from_numpy(rng.normal(size=(batch, count, 3)).astype(np.float32)), dim=-1
    )
    return points, normals


def test_knn_matches_a_kd_tree(rng):
    points = rng.normal(size=(2, 60, 3))
    centres = points[:, :15]
    knn = knn_indices(torch.from_numpy(centres), torch.from_numpy(points), 9).numpy()
    for b in range(2):
        _, expected = cKDTree(points[b]).query(centres[b], k=9)
        np.testing.assert_array_equal(knn[b], expected)
        assert (knn[b, :, 0] == np.arange(15)).all()  # a centre's nearest point is itself


@pytest.mark.parametrize("max_gathered", [None, 4])
def test_fast_edge_function_equals_the_literal_reference(rng, max_gathered):
    torch.manual_seed(0)
    edge = MultiScaleEdge(in_dim=10, edge_dim=6, scales=(4, 8, 16), max_gathered=max_gathered)
    features = torch.from_numpy(rng.normal(size=(3, 40, 10)).astype(np.float32))
    coords = torch.from_numpy(rng.normal(size=(3, 40, 3)).astype(np.float32))
    centres = coords[:, :20]
    knn = knn_indices(centres, coords, 16)
    fast = edge(features, coords, centres, knn)
    slow = reference_edge_features(edge, features, coords, centres, knn)
    assert fast.shape == (3, 20, 18)
    torch.testing.assert_close(fast, slow, rtol=1e-5, atol=1e-5)


def test_neighbour_max_gradient_equals_autograd_through_gather_and_amax(rng):
    values = torch.from_numpy(rng.normal(size=(2, 30, 5))).requires_grad_()  # float64: no ties
    index = torch.from_numpy(rng.integers(0, 30, size=(2, 12, 7)))
    weights = torch.from_numpy(rng.normal(size=(2, 12, 5)))
    (neighbour_max(values, index) * weights).sum().backward()
    fast_grad = values.grad.clone()
    values.grad = None
    batch_index = torch.arange(2).view(2, 1, 1)
    reference = values[batch_index, index].amax(dim=2)  # (2, 12, 5)
    (reference * weights).sum().backward()
    torch.testing.assert_close(fast_grad, values.grad)
    torch.testing.assert_close(neighbour_max(values, index), reference)


def test_edge_dilation_takes_every_nth_neighbour():
    from yoto.network.encoder import scale_neighbours

    knn = torch.arange(64).view(1, 1, 64)
    lists = scale_neighbours(knn, (8, 16, 32, 64), max_gathered=16)
    assert [lst.shape[-1] for lst in lists] == [8, 16, 16, 16]
    assert lists[3][0, 0].tolist() == list(range(0, 64, 4))


def test_encoder_output_shape_and_permutation_invariance(rng):
    torch.manual_seed(0)
    full = replace(TINY, centre_fraction=1.0)
    encoder = PointEncoder(full).eval()
    points, normals = _cloud(rng, 2, 48)
    features = encoder(points, normals)
    assert features.shape == (2, full.feature_dim)
    permutation = torch.from_numpy(rng.permutation(48))
    torch.testing.assert_close(encoder(points[:, permutation], normals[:, permutation]), features, rtol=1e-4, atol=1e-5)
    # A different cloud gives a different feature (the test above would pass for a constant encoder).
    other_points, other_normals = _cloud(rng, 2, 48)
    assert (encoder(other_points, other_normals) - features).abs().max() > 1e-3


def test_centre_subset_encoder_is_invariant_to_order_within_centres_and_within_the_rest(rng):
    torch.manual_seed(0)
    config = replace(TINY, centre_fraction=0.25)
    encoder = PointEncoder(config).eval()
    points, normals = _cloud(rng, 1, 48)
    centres = encoder.num_centres(48)
    assert centres == 12
    order = torch.cat([torch.from_numpy(rng.permutation(centres)), centres + torch.from_numpy(rng.permutation(36))])
    torch.testing.assert_close(
        encoder(points[:, order], normals[:, order]), encoder(points, normals), rtol=1e-4, atol=1e-5
    )


def test_cosine_logits_scale_with_the_temperature(rng):
    torch.manual_seed(0)
    net = ContactLocalizationNet(TINY)
    patch = torch.from_numpy(rng.normal(size=(3, TINY.feature_dim)).astype(np.float32))
    blocks = torch.from_numpy(rng.normal(size=(5, TINY.feature_dim)).astype(np.float32))
    assert float(net.temperature.detach()) == pytest.approx(10.0)
    logits = net.coarse_logits(patch, blocks)
    cosine = torch.nn.functional.normalize(patch, dim=1) @ torch.nn.functional.normalize(blocks, dim=1).T
    torch.testing.assert_close(logits, 10.0 * cosine)
    with torch.no_grad():
        net.log_temperature.fill_(math.log(25.0))
    torch.testing.assert_close(net.coarse_logits(patch, blocks), 25.0 * cosine)
    with torch.no_grad():
        net.log_temperature.fill_(math.log(1e4))
    assert float(net.temperature.detach()) == TINY.max_temperature
    mask = torch.ones(3, 5, dtype=torch.bool)
    mask[:, 2] = False
    assert torch.isinf(net.coarse_logits(patch, blocks, mask)[:, 2]).all()


def _forward_inputs(rng, batch=4, blocks=7):
    patch_points, patch_normals = _cloud(rng, batch, TINY.points_per_patch)
    block_points, block_normals = _cloud(rng, blocks, TINY.points_per_block)
    centres = torch.from_numpy(rng.normal(scale=0.03, size=(blocks, 3)).astype(np.float32))
    angles = rng.uniform(0, 2 * np.pi, size=blocks)
    rotations = torch.zeros(blocks, 3, 3)
    rotations[:, 0, 0] = rotations[:, 1, 1] = torch.from_numpy(np.cos(angles)).float()
    rotations[:, 0, 1] = torch.from_numpy(-np.sin(angles)).float()
    rotations[:, 1, 0] = torch.from_numpy(np.sin(angles)).float()
    rotations[:, 2, 2] = 1.0
    return {
        "patch_points": patch_points,
        "patch_normals": patch_normals,
        "block_points": block_points,
        "block_normals": block_normals,
        "block_centres": centres,
        "block_rotations": rotations,
        "block_neighbours": torch.from_numpy(block_neighbours(centres.numpy(), TINY.candidates)),
    }


def test_forward_shapes_and_candidate_geometry(rng):
    torch.manual_seed(0)
    net = ContactLocalizationNet(TINY).eval()
    data = _forward_inputs(rng)
    out = net(data)
    assert out["coarse_logits"].shape == (4, 7)
    assert out["candidates"].shape == out["confidence"].shape == (4, TINY.candidates)
    assert out["positions"].shape == (4, TINY.candidates, 3)
    # The pool is the top coarse block's neighbourhood, the top block first.
    top = out["coarse_logits"].argmax(dim=1)
    assert (out["candidates"][:, 0] == top).all()
    torch.testing.assert_close(out["candidates"], data["block_neighbours"][top])
    # p = c + R^T d for every candidate; the answer maximises coarse + confidence.
    centres, rotations = data["block_centres"][out["candidates"]], data["block_rotations"][out["candidates"]]
    expected = centres + (rotations.transpose(-1, -2) @ out["offsets"].unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(out["positions"], expected)
    scores = out["coarse_logits"].gather(1, out["candidates"]) + out["confidence"]
    torch.testing.assert_close(out["scores"], scores)
    assert (out["best"] == scores.argmax(dim=1)).all()
    torch.testing.assert_close(out["p_object"], out["positions"][torch.arange(4), out["best"]])


def test_forced_block_joins_the_pool_and_cached_block_features_match(rng):
    torch.manual_seed(0)
    net = ContactLocalizationNet(TINY).eval()
    data = _forward_inputs(rng)
    out = net(data)
    absent = [b for b in range(7) if b not in out["candidates"][0].tolist()][0]
    forced = net({**data, "force_block": torch.tensor([absent, -1, -1, -1])})
    assert absent in forced["candidates"][0].tolist()
    torch.testing.assert_close(forced["candidates"][1:], out["candidates"][1:])
    cached = net({**data, "block_features": out["block_features"]})
    torch.testing.assert_close(cached["positions"], out["positions"])


def test_block_neighbours_put_each_block_first():
    centres = np.array([[0.0, 0, 0], [1.0, 0, 0], [3.0, 0, 0], [0.0, 0, 0.5]])
    neighbours = block_neighbours(centres, 3)
    assert neighbours.tolist() == [[0, 3, 1], [1, 0, 3], [2, 1, 0], [3, 0, 1]]


@pytest.mark.parametrize("name", ["paper", "cpu-points"])
def test_presets_build_and_round_trip(name):
    config = PRESETS[name]
    assert NetworkConfig.from_dict(config.to_dict()) == config
    net = ContactLocalizationNet(config)
    parameters = sum(p.numel() for p in net.parameters())
    assert parameters > 50_000
    with pytest.raises(ValueError, match="unknown network config keys"):
        NetworkConfig.from_dict({**config.to_dict(), "typo": 1})


def test_paper_preset_has_the_papers_sizes():
    paper = PRESETS["paper"]
    assert (paper.point_dim, paper.fusion_dim, paper.prepool_dim, paper.feature_dim) == (256, 256, 512, 512)
    assert paper.knn_scales == (8, 16, 32, 64) and paper.points_per_patch == paper.points_per_block == 512
    assert paper.candidates == 9 and paper.fine_dims == (512, 256) and paper.fine_dropout == 0.2
    assert paper.initial_temperature == 10.0 and paper.centre_fraction == 1.0
