"""Forward warp: equals a direct per-voxel implementation of the paper's formula (negative
displacements included), is differentiable, deterministic when asked, batch-independent."""

import itertools

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.models.warp import forward_warp  # noqa: E402


def direct_warp(features, flow, weight, eps=1e-3):
    """The paper's formula, voxel by voxel: W(i -> j) = m_i prod max(0, 1 - |x_i + f_i - x_j|)."""
    c, *dims = features.shape
    out = np.zeros_like(features)
    norm = np.zeros(dims)
    for i in itertools.product(*(range(d) for d in dims)):
        target = np.array(i) + flow[(slice(None),) + i]
        for j in itertools.product(*(range(d) for d in dims)):
            w = weight[i] * np.prod(np.maximum(0.0, 1 - np.abs(target - np.array(j))))
            if w:
                out[(slice(None),) + j] += w * features[(slice(None),) + i]
                norm[j] += w
    return out / np.maximum(norm, eps)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_the_direct_formula_with_negative_displacements(seed):
    rng = np.random.default_rng(seed)
    dims = (4, 5, 3)
    features = rng.normal(size=(2,) + dims)
    flow = rng.uniform(-2.5, 2.5, size=(3,) + dims)  # negative targets and out-of-bounds included
    weight = rng.uniform(0, 1, size=dims)
    expected = direct_warp(features, flow, weight)
    got = forward_warp(torch.tensor(features)[None], torch.tensor(flow)[None], torch.tensor(weight)[None]).numpy()[0]
    assert np.allclose(got, expected, atol=1e-5)


def test_integer_shift_moves_features_exactly():
    f = torch.zeros(1, 1, 6, 6, 6)
    f[0, 0, 3, 3, 3] = 7.0
    flow = torch.zeros(1, 3, 6, 6, 6)
    flow[0, :, 3, 3, 3] = torch.tensor([-2.0, 1.0, -3.0])
    weight = torch.zeros(1, 6, 6, 6)
    weight[0, 3, 3, 3] = 1.0  # only the moving voxel is foreground
    out = forward_warp(f, flow, weight)
    assert out[0, 0, 1, 4, 0] == 7.0 and out.abs().sum() == 7.0  # floor, not truncation, for negatives
    flow[0, :, 3, 3, 3] = torch.tensor([-3.5, 0.0, 0.0])  # lands at -0.5: half of it at voxel 0, half dropped
    out = forward_warp(f, flow, weight)
    assert out[0, 0, 0, 3, 3] == 7.0 and out.abs().sum() == 7.0  # normalised by the weight that arrived
    flow[0, :, 3, 3, 3] = torch.tensor([-4.5, 0.0, 0.0])  # both corners (-5, -4) outside: nothing lands
    assert forward_warp(f, flow, weight).abs().sum() == 0


def test_gradients_and_gradcheck():
    rng = np.random.default_rng(3)
    dims = (3, 3, 2)
    f = torch.tensor(rng.normal(size=(1, 2) + dims), requires_grad=True)
    flow = torch.tensor(rng.uniform(-0.9, 0.9, size=(1, 3) + dims), requires_grad=True)
    w = torch.tensor(rng.uniform(0.2, 1, size=(1,) + dims), requires_grad=True)

    out = forward_warp(f, flow, w)
    assert out.dtype == torch.float64  # fp64 inputs are warped in fp64
    # flow within (-1, 1) and away from integer positions: the splat is smooth there
    assert torch.autograd.gradcheck(forward_warp, (f, flow, w), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_gradient_flows_into_the_target_voxels():
    f = torch.zeros(1, 1, 4, 4, 4, dtype=torch.float64)
    f[0, 0, 1, 1, 1] = 2.0
    w = torch.zeros(1, 4, 4, 4, dtype=torch.float64)
    w[0, 1, 1, 1] = 1.0
    w[0, 2, 1, 1] = 1.0  # a static neighbour with feature 0 shares the target voxels
    flow = torch.zeros(1, 3, 4, 4, 4, dtype=torch.float64, requires_grad=True)
    with torch.no_grad():
        flow[0, 0, 1, 1, 1] = 0.25
    out = forward_warp(f, flow, w)
    # voxel (1,1,1) receives 0.75 of the moving feature and nothing else: value 2.0 exactly
    assert out[0, 0, 1, 1, 1].item() == pytest.approx(2.0)
    # voxel (2,1,1) mixes 0.25 x 2.0 with the static neighbour's 1.0 x 0.0
    assert out[0, 0, 2, 1, 1].item() == pytest.approx(0.5 / 1.25)
    out[0, 0, 2, 1, 1].backward()
    # d/dflow of (2 a) / (a + 1) with a = flow: 2 / (a + 1)^2
    assert flow.grad[0, 0, 1, 1, 1].item() == pytest.approx(2 / 1.25 ** 2)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="disagree"):
        forward_warp(torch.zeros(1, 2, 4, 4, 4), torch.zeros(1, 3, 4, 4, 2), torch.zeros(1, 4, 4, 4))


def test_deterministic_mode_and_batch_independence():
    torch.manual_seed(0)
    f = torch.randn(3, 4, 8, 8, 8)
    flow = torch.randn(3, 3, 8, 8, 8) * 2
    w = torch.rand(3, 8, 8, 8)
    a = forward_warp(f, flow, w, deterministic=True)
    b = forward_warp(f, flow, w, deterministic=True)
    assert torch.equal(a, b)
    assert torch.allclose(a, forward_warp(f, flow, w), atol=1e-5)
    single = forward_warp(f[1:2], flow[1:2], w[1:2])
    assert torch.allclose(a[1:2], single, atol=1e-5)
