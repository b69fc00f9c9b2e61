"""The network (tiny config): shapes, rotation invariance, learning, loss, ONNX parity."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from escape_cli.core.anchors import select_anchors  # noqa: E402
from escape_cli.core.encoding import distance_matrix  # noqa: E402
from escape_cli.nn.config import ModelConfig, get_preset  # noqa: E402
from escape_cli.nn.loss import chamfer_l1, chamfer_l1_naive  # noqa: E402
from escape_cli.nn.model import EscapeNet  # noqa: E402
from escape_cli.core.rotations import random_rotation  # noqa: E402
from escape_cli.core.sampling import prepare_input  # noqa: E402
from tests_support import with_moving_refiners  # noqa: E402

TINY = get_preset("tiny")
TINY_REFINED = get_preset("tiny-refine")


def network(config: ModelConfig, seed: int = 0) -> EscapeNet:
    """EscapeNet(config) in eval mode; its refiners' offset layers random, not zero (so they move points)."""
    torch.manual_seed(seed)
    return with_moving_refiners(EscapeNet(config).eval())


def partial_cloud(rng: np.random.Generator, n: int = 600) -> np.ndarray:
    """(n, 3) points on one side of a random ellipsoid: a stand-in for a partial scan."""
    pts = rng.normal(size=(n * 2, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    pts *= rng.uniform(0.2, 0.5, size=3)
    return pts[pts[:, 0] > 0][:n]


def features(points: np.ndarray, config: ModelConfig = TINY) -> np.ndarray:
    prepared, unique = prepare_input(points, config.input_points)
    anchors = select_anchors(prepared[:unique], config.anchors)
    return distance_matrix(prepared, anchors.points).astype(np.float32)


@pytest.mark.parametrize("config", [TINY, TINY_REFINED], ids=["fold", "refined"])
def test_forward_shapes(config):
    net = network(config)
    x = torch.rand(3, TINY.input_points, TINY.anchors)
    fine, coarse = net(x)
    assert fine.shape == (3, TINY.output_points, TINY.anchors)
    assert coarse.shape == (3, TINY.queries, TINY.anchors)
    seeds = torch.tensor([0, 3])
    fine_sub, _ = net(x, seeds)
    assert fine_sub.shape == (3, TINY.queries * 2, TINY.anchors)
    # a subset of fold seeds gives exactly those rows of the full output
    full = fine.view(3, TINY.queries, TINY.fold, TINY.anchors)[:, :, [0, 3]].reshape(3, -1, TINY.anchors)
    assert torch.allclose(full, fine_sub, atol=1e-6)


def test_refiners_move_points_and_train_like_they_evaluate():
    net = network(TINY_REFINED)
    x = torch.rand(2, TINY.input_points, TINY.anchors)
    without = network(TINY)  # the same seed draws the same weights for the shared layers
    without.load_state_dict({k: v for k, v in net.state_dict().items() if not k.startswith("refine.")})
    with torch.no_grad():
        refined, coarse = net(x)
        folded, coarse_before = without(x)
        assert torch.equal(coarse, coarse_before)  # refiners act on the fine points alone
        assert float((refined - folded).abs().max()) > 1e-3
        trained = net.train()(x)[0]  # the training form (embedding lookups) computes the same
    assert torch.allclose(trained, refined, atol=1e-5)


@pytest.mark.parametrize("config", [TINY, TINY_REFINED], ids=["fold", "refined"])
def test_output_unchanged_under_rotation_and_translation(rng, config):
    net = network(config)
    cloud = partial_cloud(rng)
    base = net(torch.from_numpy(features(cloud)[None]))[0]
    for i in range(20):
        r = random_rotation(rng)
        t = rng.normal(scale=5.0, size=3)
        moved = cloud @ r.T + t
        moved = moved[rng.permutation(len(moved))]
        out = net(torch.from_numpy(features(moved)[None]))[0]
        assert torch.allclose(out, base, atol=1e-4), f"rotation {i}: {float((out - base).abs().max())}"


def test_loss_matches_brute_force(rng):
    pred = torch.from_numpy(rng.random((2, 300, 8)).astype(np.float32)).requires_grad_()
    gt = torch.from_numpy(rng.random((2, 200, 8)).astype(np.float32))
    fast = chamfer_l1(pred, gt)
    slow = chamfer_l1_naive(pred, gt)
    assert fast.item() == pytest.approx(slow.item(), rel=1e-5)
    (g_fast,) = torch.autograd.grad(fast, pred)
    (g_slow,) = torch.autograd.grad(slow, pred)
    assert torch.allclose(g_fast, g_slow, atol=1e-6)
    assert chamfer_l1(gt, gt).item() == pytest.approx(0.0, abs=1e-7)


def test_recall_weight_weighs_the_truth_to_prediction_half(rng):
    pred = torch.from_numpy(rng.random((2, 300, 8)).astype(np.float32))
    gt = torch.from_numpy(rng.random((2, 200, 8)).astype(np.float32))
    d = torch.cdist(pred, gt)  # (B, P, G)
    precision = d.min(dim=2).values.mean(dim=1)  # (B,) prediction -> truth
    recall = d.min(dim=1).values.mean(dim=1)  # (B,) truth -> prediction
    expected = ((precision + 3.0 * recall) / 4.0).mean()
    assert chamfer_l1(pred, gt, recall_weight=3.0).item() == pytest.approx(expected.item(), rel=1e-5)
    assert chamfer_l1(pred, gt, recall_weight=1.0).item() == pytest.approx(chamfer_l1(pred, gt).item(), rel=1e-7)


def test_a_few_steps_lower_the_loss(rng):
    torch.manual_seed(0)
    net = EscapeNet(TINY)
    x = torch.from_numpy(np.stack([features(partial_cloud(rng)) for _ in range(2)]))
    target = x[:, :64] * 1.1 + 0.05  # a fixed, learnable target in distance space
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(30):
        fine, coarse = net(x)
        loss = chamfer_l1(fine, target) + chamfer_l1(coarse, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_differentiable_reconstruction_is_the_lm_solution_with_its_implicit_gradient(rng):
    from escape_cli.nn.loss import reconstruct_differentiable
    from escape_cli.core.reconstruction import reconstruct

    anchors = rng.normal(size=(8, 3))
    points = 0.5 * rng.normal(size=(6, 3))
    exact = np.linalg.norm(points[:, None] - anchors[None], axis=-1)  # (6, 8)
    d = torch.tensor(exact[None], requires_grad=True)
    out = reconstruct_differentiable(d, torch.tensor(anchors[None]), points[None], damping=0.0)  # (1, 6, 3)
    np.testing.assert_allclose(out.detach().numpy()[0], points, atol=1e-8)
    grad = torch.autograd.grad(out[0, 2, 1], d)[0].numpy()[0]  # (6, 8)
    eps = 1e-6
    numeric = np.zeros(8)
    for k in range(8):
        up, down = exact.copy(), exact.copy()
        up[2, k] += eps
        down[2, k] -= eps
        numeric[k] = (reconstruct(up, anchors).points[2, 1] - reconstruct(down, anchors).points[2, 1]) / (2 * eps)
    np.testing.assert_allclose(grad[2], numeric, atol=1e-5)
    assert np.abs(np.delete(grad, 2, axis=0)).max() == 0.0  # points are solved independently
