"""Forward warp: equals a direct per-voxel implementation of the paper's formula (negative
displacements included), is differentiable, deterministic when asked, batch-independent. The authors'
kernel (kernel=OFFICIAL: base corner truncated toward zero) on hand-made flows whose result is worked
out by hand, against a plain-Python port of the kernel's per-voxel rule, equal to ours for targets >= 0."""

import itertools

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from dsr_bench.models.warp import FLOOR, OFFICIAL, WARP_KERNELS, forward_warp  # noqa: E402


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


# --- the authors' kernel (kernel=OFFICIAL) ---------------------------------------------------------------


def official_reference(features, flow, weight, eps=1e-3):
    """The authors' kernel's rule, voxel by voxel (../shared/notes/official-release.md, "The forward warp
    kernel, exactly"): target f = v + flow per axis, base corner int(f) (truncation toward zero), corners
    base + d (d in {0, 1}) used only inside the grid, weight mask(v) * prod((base + 1 - f) if d == 0 else
    (f - base)); weights and weighted features summed, cnt = max(cnt, eps), output = sum / cnt."""
    c, *dims = features.shape
    out = np.zeros_like(features)
    cnt = np.zeros(dims)
    for v in itertools.product(*(range(d) for d in dims)):
        f = [v[a] + flow[(a,) + v] for a in range(3)]
        base = [int(x) for x in f]  # Python's int() truncates toward zero, as C's does
        for d in itertools.product((0, 1), repeat=3):
            corner = tuple(base[a] + d[a] for a in range(3))
            if not all(0 <= corner[a] < dims[a] for a in range(3)):
                continue
            w = weight[v]
            for a in range(3):
                w *= (base[a] + 1 - f[a]) if d[a] == 0 else (f[a] - base[a])
            cnt[corner] += w
            out[(slice(None),) + corner] += w * features[(slice(None),) + v]
    return out / np.maximum(cnt, eps)


def line(moves: dict[int, tuple[float, float, float]], n: int = 5):
    """A (n, 1, 1) grid, fp64: {source index: (target along D0, feature, mask)}; every other voxel has mask 0.
    Along D1 and D2 (size 1, flow 0) the base is 0 with weight 1 and the corner 1 is outside: a 1D splat."""
    features = torch.zeros(1, 1, n, 1, 1, dtype=torch.float64)
    flow = torch.zeros(1, 3, n, 1, 1, dtype=torch.float64)
    weight = torch.zeros(1, n, 1, 1, dtype=torch.float64)
    for source, (target, value, mask) in moves.items():
        flow[0, 0, source] = target - source
        features[0, 0, source] = value
        weight[0, source] = mask
    return features, flow, weight


def warped(moves: dict, kernel: str, n: int = 5) -> list[float]:
    return forward_warp(*line(moves, n), kernel=kernel)[0, 0, :, 0, 0].tolist()


def test_targets_in_minus_one_to_zero_get_a_negative_weight():
    # 8 lands at -0.25. Authors': base int(-0.25) = 0, voxel 0 gets 1.25, voxel 1 gets -0.25, so voxel 1 holds
    # 8 * -0.25 / max(-0.25, 1e-3) = -2000. Ours: base -1 (dropped), voxel 0 gets 0.75: 8 there, nothing at 1.
    assert warped({0: (-0.25, 8.0, 1.0)}, OFFICIAL) == pytest.approx([8.0, -2000.0, 0, 0, 0])
    assert warped({0: (-0.25, 8.0, 1.0)}, FLOOR) == pytest.approx([8.0, 0, 0, 0, 0])
    # a static voxel at 1 (feature 2, mask m) shares voxel 1: sum of weights m - 0.25, features 2 m - 2
    assert warped({0: (-0.25, 8.0, 1.0), 1: (1.0, 2.0, 1.0)}, OFFICIAL)[1] == pytest.approx(0.0)  # 0 / 0.75
    assert warped({0: (-0.25, 8.0, 1.0), 1: (1.0, 2.0, 0.5)}, OFFICIAL)[1] == pytest.approx(-4.0)  # -1 / 0.25
    # the weights cancel (sum 0 < 1e-3): divided by 1e-3
    assert warped({0: (-0.25, 8.0, 1.0), 1: (1.0, 2.0, 0.25)}, OFFICIAL)[1] == pytest.approx(-1500.0)
    # the mask scales the weights of both corners; voxel 0 is normalised by its own positive weight
    assert warped({0: (-0.5, 4.0, 0.5)}, OFFICIAL) == pytest.approx([4.0, 4.0 * 0.5 * -0.5 / 1e-3, 0, 0, 0])


def test_targets_in_minus_two_to_minus_one_put_a_non_positive_weight_on_voxel_zero():
    # 8 lands at -1.5: base int(-1.5) = -1 is outside, voxel 0 gets f - base = -0.5: 8 * -0.5 / 1e-3 = -4000.
    # Ours: floor(-1.5) = -2, both corners (-2, -1) outside: nothing lands.
    assert warped({1: (-1.5, 8.0, 1.0)}, OFFICIAL) == pytest.approx([-4000.0, 0, 0, 0, 0])
    assert warped({1: (-1.5, 8.0, 1.0)}, FLOOR) == [0.0] * 5
    # exactly -1: base -1, voxel 0's weight is 0: nothing (0 / 1e-3)
    assert warped({2: (-1.0, 8.0, 1.0)}, OFFICIAL) == [0.0] * 5
    # a voxel resting at 0 (feature 2, mask 1) with it: weights 1 - 0.5 = 0.5, features 2 - 4 = -2: -4
    assert warped({1: (-1.5, 8.0, 1.0), 0: (0.0, 2.0, 1.0)}, OFFICIAL)[0] == pytest.approx(-4.0)


@pytest.mark.parametrize("target", [-2.0, -2.5, -3.75])
def test_targets_at_or_below_minus_two_land_nowhere(target):
    for kernel in WARP_KERNELS:
        assert warped({3: (target, 8.0, 1.0)}, kernel) == [0.0] * 5
    # with a resting voxel beside it, only that one's feature is left
    assert warped({3: (target, 8.0, 1.0), 0: (0.0, 2.0, 0.5)}, OFFICIAL) == pytest.approx([2.0, 0, 0, 0, 0])


def test_a_negative_target_on_one_axis_and_a_fraction_on_another():
    """Source (0, 1, 0) of a (3, 3, 2) grid, feature 4, lands at (-0.5, 1.25, 0): the authors' weights are
    D0 {0: 1.5, 1: -0.5} x D1 {1: 0.75, 2: 0.25} x D2 {0: 1, 1: 0}."""
    f = torch.zeros(1, 1, 3, 3, 2, dtype=torch.float64)
    flow = torch.zeros(1, 3, 3, 3, 2, dtype=torch.float64)
    w = torch.zeros(1, 3, 3, 2, dtype=torch.float64)
    f[0, 0, 0, 1, 0], w[0, 0, 1, 0] = 4.0, 1.0
    flow[0, :, 0, 1, 0] = torch.tensor([-0.5, 0.25, 0.0], dtype=torch.float64)
    expected = torch.zeros(3, 3, 2, dtype=torch.float64)
    expected[0, 1, 0] = expected[0, 2, 0] = 4.0  # positive weights 1.125 and 0.375: the feature itself
    expected[1, 1, 0] = 4 * (-0.5 * 0.75) / 1e-3  # -1500
    expected[1, 2, 0] = 4 * (-0.5 * 0.25) / 1e-3  # -500
    assert torch.allclose(forward_warp(f, flow, w, kernel=OFFICIAL)[0, 0], expected)
    ours = torch.zeros(3, 3, 2, dtype=torch.float64)
    ours[0, 1, 0] = ours[0, 2, 0] = 4.0  # D0: base -1 dropped, voxel 0 gets 0.5; nothing on D0 = 1
    assert torch.allclose(forward_warp(f, flow, w)[0, 0], ours)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_for_targets_at_or_above_zero_the_kernels_agree_bit_for_bit(dtype):
    gen = torch.Generator().manual_seed(4)
    dims = (6, 7, 5)
    features = torch.randn(2, 3, *dims, generator=gen, dtype=dtype)
    grid = torch.stack(torch.meshgrid(*(torch.arange(d, dtype=dtype) for d in dims), indexing="ij"))
    flow = torch.maximum(torch.rand(2, 3, *dims, generator=gen, dtype=dtype) * 6 - 3, -grid)  # targets >= 0
    assert bool(((grid + flow) >= 0).all()) and bool((flow < 0).any())
    weight = torch.rand(2, *dims, generator=gen, dtype=dtype)
    assert torch.equal(forward_warp(features, flow, weight, kernel=OFFICIAL), forward_warp(features, flow, weight))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_official_kernel_matches_its_per_voxel_rule(seed):
    """Random targets in (-3, D + 3) on every axis: negative (every case above), beyond the far side, inside."""
    rng = np.random.default_rng(seed)
    dims = (4, 5, 3)
    features = rng.normal(size=(2, 2) + dims)
    flow = rng.uniform(-3, 3, size=(2, 3) + dims)
    weight = rng.uniform(0, 1, size=(2,) + dims)
    got = forward_warp(torch.tensor(features), torch.tensor(flow), torch.tensor(weight), kernel=OFFICIAL).numpy()
    for b in range(2):
        expected = official_reference(features[b], flow[b], weight[b])
        assert np.allclose(got[b], expected, rtol=1e-10, atol=1e-9)
    assert not np.allclose(got, forward_warp(torch.tensor(features), torch.tensor(flow), torch.tensor(weight)).numpy())
    fp32 = forward_warp(torch.tensor(features).float(), torch.tensor(flow).float(), torch.tensor(weight).float(),
                        kernel=OFFICIAL)
    assert fp32.dtype == torch.float32 and np.isfinite(fp32.numpy()).all()


def test_the_official_kernel_is_differentiable():
    """Gradients in features, flow and weights, with targets in (-1, 0) (negative weights) on every axis;
    weights near 1, so no voxel's summed weight is near the eps kink."""
    rng = np.random.default_rng(5)
    dims = (3, 3, 2)
    f = torch.tensor(rng.normal(size=(1, 2) + dims), requires_grad=True)
    flow = torch.tensor(rng.uniform(-0.9, 0.9, size=(1, 3) + dims), requires_grad=True)
    w = torch.tensor(rng.uniform(0.6, 1, size=(1,) + dims), requires_grad=True)
    assert bool((flow[0, 0, 0] < 0).any())  # some targets on D0 in (-1, 0)

    def official(features, flow, weight):
        return forward_warp(features, flow, weight, kernel=OFFICIAL)

    assert torch.autograd.gradcheck(official, (f, flow, w), eps=1e-6, atol=1e-6, rtol=1e-5)
    # by hand: one voxel (feature 8) moving to a in (-1, 0) and a resting one (feature 2, mask 1) at voxel 1;
    # voxel 1 holds (8 a + 2) / (a + 1), whose derivative in a is (8 - 2) / (a + 1)^2
    features, flow, weight = line({0: (-0.25, 8.0, 1.0), 1: (1.0, 2.0, 1.0)})
    flow.requires_grad_(True)
    forward_warp(features, flow, weight, kernel=OFFICIAL)[0, 0, 1, 0, 0].backward()
    assert flow.grad[0, 0, 0, 0, 0].item() == pytest.approx(6 / 0.75 ** 2)


def test_an_unknown_kernel_is_refused():
    with pytest.raises(ValueError, match="warp kernel 'round': choose one of floor, official"):
        forward_warp(torch.zeros(1, 1, 2, 2, 2), torch.zeros(1, 3, 2, 2, 2), torch.zeros(1, 2, 2, 2), kernel="round")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("kernel", WARP_KERNELS)
def test_the_kernels_on_a_gpu_equal_the_cpu(kernel):
    gen = torch.Generator().manual_seed(6)
    dims = (16, 16, 8)
    args = (torch.randn(2, 4, *dims, generator=gen), torch.rand(2, 3, *dims, generator=gen) * 8 - 4,
            torch.rand(2, *dims, generator=gen))
    cpu = forward_warp(*args, kernel=kernel)
    gpu = forward_warp(*(a.cuda() for a in args), kernel=kernel).cpu()
    det = forward_warp(*(a.cuda() for a in args), kernel=kernel, deterministic=True).cpu()
    scale = cpu.abs().max()  # the official kernel divides near-cancelling sums by 1e-3: compare on its scale
    assert torch.allclose(gpu, cpu, atol=1e-4 * float(scale)) and torch.allclose(det, cpu, atol=1e-4 * float(scale))
