"""Loss terms on hand-computed cases."""

from __future__ import annotations

import math

import pytest

torch = pytest.importorskip("torch")

from yoto.training.losses import (  # noqa: E402
    LossConfig,
    block_cross_entropy,
    candidate_weights,
    localization_loss,
    position_loss,
    selection_loss,
    topk_margin,
    topk_recall,
)


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    """Small tensors gain nothing from threads, and on a shared machine extra threads only spin."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_block_cross_entropy_by_hand():
    logits = torch.tensor([[2.0, 0.0, -1.0], [0.0, 0.0, float("-inf")]])
    loss = block_cross_entropy(logits, torch.tensor([0, 1]))
    expected0 = -2.0 + math.log(math.exp(2.0) + 1.0 + math.exp(-1.0))
    expected1 = math.log(2.0)  # the masked block takes no probability
    torch.testing.assert_close(loss, torch.tensor([expected0, expected1]))


def test_topk_margin_by_hand():
    logits = torch.tensor([[5.0, 4.0, 3.0, 1.0, 0.0]])
    # Truth ranked 3rd (3.0): best other 5.0 -> [5 - 3 + 0.5]+ = 2.5; K = 2 -> 2nd logit 4.0: [4 - 3 + 1]+ = 2.
    assert topk_margin(logits, torch.tensor([2]), k=2, margin_top=0.5, margin_k=1.0).item() == pytest.approx(4.5)
    # Truth on top by 1.0 > m1: first term 0; K = 2: [4 - 5 + 1]+ = 0.
    assert topk_margin(logits, torch.tensor([0]), k=2, margin_top=0.5, margin_k=1.0).item() == pytest.approx(0.0)
    # Truth on top by less than m1 = 1.5: 4 - 5 + 1.5 = 0.5; K = 4 -> 4th logit 1.0: [1 - 5 + 1]+ = 0.
    assert topk_margin(logits, torch.tensor([0]), k=4, margin_top=1.5, margin_k=1.0).item() == pytest.approx(0.5)
    # Truth last: [5 - 0 + 0.5] + [3 - 0 + 1] with K = 3.
    assert topk_margin(logits, torch.tensor([4]), k=3, margin_top=0.5, margin_k=1.0).item() == pytest.approx(9.5)


def test_topk_recall():
    logits = torch.tensor([[5.0, 4.0, 3.0], [0.0, 1.0, 2.0]])
    assert topk_recall(logits, torch.tensor([1, 0]), 2).tolist() == [True, False]
    assert topk_recall(logits, torch.tensor([1, 0]), 3).tolist() == [True, True]


def test_position_loss_is_weighted_smooth_l1_in_position_units():
    positions = torch.tensor([[[0.001, 0.0, 0.0], [0.0, 0.03, 0.0]]])  # 1 mm and 30 mm off
    truth = torch.zeros(1, 3)
    weights = torch.tensor([[0.25, 0.75]])
    loss = position_loss(positions, truth, weights, unit_m=0.01, beta=0.2)
    # 0.1 units < beta: 0.5 x 0.1^2 / 0.2 = 0.025; 3 units > beta: 3 - 0.1 = 2.9.
    assert loss.item() == pytest.approx(0.25 * 0.025 + 0.75 * 2.9, rel=1e-5)


def test_candidate_weights_favour_high_scores_and_near_centres():
    scores = torch.tensor([[0.0, 0.0, 10.0]])
    centres = torch.tensor([[[0.0, 0, 0], [0.05, 0, 0], [0.1, 0, 0]]])
    weights = candidate_weights(scores, centres, torch.zeros(1, 3), distance_m=0.01)
    assert weights.sum().item() == pytest.approx(1.0)
    # Candidate 0 is nearest, candidate 2 has the top score; candidate 1 has neither.
    assert weights[0, 1] < weights[0, 0] and weights[0, 1] < weights[0, 2]
    assert not weights.requires_grad


def test_selection_loss_targets_the_candidate_nearest_the_truth():
    logits = torch.tensor([[1.0, 0.0, 0.0]])
    candidates = torch.tensor([[0, 1, 2]])
    confidence = torch.zeros(1, 3, requires_grad=True)
    positions = torch.tensor([[[0.02, 0, 0], [0.001, 0, 0], [0.03, 0, 0]]])
    loss = selection_loss(logits, candidates, confidence, positions, torch.zeros(1, 3))
    expected = -0.0 + math.log(math.e + 2.0)  # target is candidate 1, whose combined score is 0
    assert loss.item() == pytest.approx(expected)
    loss.sum().backward()
    assert confidence.grad[0, 1] < 0 < confidence.grad[0, 0]  # raise the right one, lower the others


def test_total_loss_combines_the_terms_with_the_adaptive_weight():
    config = LossConfig(topk=1)
    logits = torch.tensor([[0.0, 3.0], [3.0, 0.0]], requires_grad=True)
    outputs = {
        "coarse_logits": logits,
        "candidates": torch.tensor([[1, 0], [0, 1]]),
        "confidence": torch.zeros(2, 2),
        "positions": torch.zeros(2, 2, 3),
        "scores": torch.zeros(2, 2),
    }
    target = torch.tensor([0, 0])  # first sample wrong at top-1, second right
    total, parts = localization_loss(outputs, target, torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(2), config)
    assert parts["topk_recall"] == pytest.approx(0.5)
    assert parts["adaptive"] == pytest.approx(1.0 + 1.5 * 0.5)
    coarse = parts["cls"] + parts["topk_margin"]
    expected = parts["adaptive"] * coarse + config.pos_weight * parts["pos"] + config.select_weight * parts["select"]
    assert total.item() == pytest.approx(expected, rel=1e-5)
    assert parts["pos"] == pytest.approx(0.0)
    # Weighting a sample up moves the mean toward it.
    _, weighted = localization_loss(
        outputs, target, torch.zeros(2, 3), torch.zeros(2, 3), torch.tensor([1.0, 3.0]), config
    )
    assert weighted["cls"] < parts["cls"]
