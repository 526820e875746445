"""The SDF's trilinear reads against torch's grid_sample, which they replace."""
import torch
import torch.nn.functional as F

from prox_engine.scene_sdf import SignedDistanceField
from prox_engine.trilinear import Trilinear


def grid_sample_reads(grid: torch.Tensor, bmin: torch.Tensor, bmax: torch.Tensor,
                      points: torch.Tensor) -> torch.Tensor:
    """The SDF's reads as torch computed them before the kernel: the [x, y, z] grid as
    (N, C, D=z, H=y, W=x), border padding, corners aligned."""
    volume = grid.permute(2, 1, 0)[None, None]
    norm = (points.reshape(1, -1, 1, 1, 3) - bmin) / (bmax - bmin) * 2 - 1
    out = F.grid_sample(volume, norm, mode="bilinear", padding_mode="border",
                        align_corners=True)
    return out.reshape(points.shape[:-1])


def test_reads_and_gradients_are_grid_samples_on_an_uneven_box():
    torch.manual_seed(0)
    grid = torch.randn(7, 11, 5)  # a different size on every axis: a mix-up fails
    bmin, bmax = torch.tensor([-1.0, 0.5, 2.0]), torch.tensor([2.0, 1.5, 2.4])
    inside = bmin + torch.rand(400, 3) * (bmax - bmin)
    outside = bmin + (torch.rand(100, 3) * 1.6 - 0.3) * (bmax - bmin)  # some past each face
    points = torch.cat([inside, outside]).reshape(5, 100, 3).requires_grad_()
    reads = Trilinear(grid, bmin, bmax)(points)
    expected = grid_sample_reads(grid, bmin, bmax, points)
    assert reads.shape == (5, 100)
    torch.testing.assert_close(reads, expected, rtol=0, atol=1e-5)
    weights = torch.randn(5, 100)
    (ours,) = torch.autograd.grad((reads * weights).sum(), points)
    (theirs,) = torch.autograd.grad((expected * weights).sum(), points)
    torch.testing.assert_close(ours, theirs, rtol=1e-4, atol=1e-4)
    across = (points.detach() < bmin) | (points.detach() > bmax)
    assert across.any() and (ours[across] == 0).all()  # no gradient across the border


def test_a_linear_field_is_read_exactly_in_world_axes():
    bmin, bmax = torch.tensor([-2.0, 1.0, 0.0]), torch.tensor([1.0, 3.0, 4.0])
    axes = [torch.linspace(float(lo), float(hi), n) for lo, hi, n in zip(bmin, bmax, (9, 13, 6))]
    x, y, z = torch.meshgrid(*axes, indexing="ij")
    sdf = SignedDistanceField(0.5 * x - 2.0 * y + 3.0 * z, bmin, bmax)
    points = (bmin + torch.rand(50, 3) * (bmax - bmin)).requires_grad_()
    values = sdf(points)
    p = points.detach()
    torch.testing.assert_close(values, 0.5 * p[:, 0] - 2.0 * p[:, 1] + 3.0 * p[:, 2],
                               rtol=0, atol=1e-5)
    (gradient,) = torch.autograd.grad(values.sum(), points)
    torch.testing.assert_close(gradient, torch.tensor([0.5, -2.0, 3.0]).expand(50, 3))


def test_reads_keep_the_points_dtype_and_pass_nan_on():
    grid = torch.zeros(4, 4, 4)
    reader = Trilinear(grid, torch.zeros(3), torch.ones(3))
    points = torch.tensor([[0.5, 0.5, 0.5], [float("nan"), 0.5, 0.5]], dtype=torch.float64)
    values = reader(points)
    assert values.dtype == torch.float64
    assert values[0] == 0 and torch.isnan(values[1])
    assert reader(torch.zeros(0, 3)).shape == (0,)


def test_threads_reading_at_once_each_get_their_own_reads():
    """A kernel's recorded launch is one mutable argument list, so each thread records its
    own: threads launching at once with different points and sizes read what they would
    read alone."""
    from concurrent.futures import ThreadPoolExecutor

    torch.manual_seed(1)
    bmin, bmax = torch.zeros(3), torch.ones(3)
    reader = Trilinear(torch.randn(9, 7, 5), bmin, bmax)
    batches = [torch.rand(n, 3) for n in (1, 17, 300, 4096) for _ in range(8)]
    alone = [reader(points) for points in batches]
    with ThreadPoolExecutor(4) as pool:
        together = list(pool.map(lambda points: [reader(points) for _ in range(20)], batches))
    for reads, expected in zip(together, alone):
        for read in reads:
            assert torch.equal(read, expected)


def test_reads_in_another_frame_are_the_worlds_at_the_moved_points():
    """A reader given a tilted, turned, shifted frame reads at p what the world's reader
    reads at R p + t, and its gradient is R^T times the world's (so an axis mix-up fails)."""
    from scipy.spatial.transform import Rotation

    torch.manual_seed(1)
    grid = torch.randn(9, 6, 11)
    bmin, bmax = torch.tensor([-1.0, -0.5, 0.2]), torch.tensor([1.5, 1.0, 2.0])
    frame = torch.eye(4)
    frame[:3, :3] = torch.tensor(Rotation.from_euler("xyz", [25, -40, 110], degrees=True)
                                 .as_matrix(), dtype=torch.float32)
    frame[:3, 3] = torch.tensor([0.3, 0.1, 1.2])
    sdf = SignedDistanceField(grid, bmin, bmax)
    world = bmin + torch.rand(300, 3) * (bmax - bmin)
    local = ((world - frame[:3, 3]) @ frame[:3, :3]).requires_grad_()
    moved = local @ frame[:3, :3].T + frame[:3, 3]
    ours = sdf.seen_from(frame)(local)
    theirs = sdf(moved)
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-5)
    (gradient,) = torch.autograd.grad(ours.sum(), local)
    (expected,) = torch.autograd.grad(theirs.sum(), local)
    torch.testing.assert_close(gradient, expected, rtol=1e-4, atol=1e-4)
