"""Losses against hand-computed values on tiny inputs, and the VGG16 file handling."""

from __future__ import annotations

import math
import urllib.error

import pytest
import torch
import torch.nn.functional as F

from tests.support.checkpoints import deflated_torch_file
from unicorn.errors import UserError
from unicorn.geometry.mesh import ellipsoid
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.model import TemplateMesh
from unicorn.model.pose import PoseHead, PoseOutput, mirrored_pose
from unicorn.objectives import (
    MeshRegularizer,
    NormalConsistencyLoss,
    ReconstructionLoss,
    StructuralLoss,
    UniformLaplacianLoss,
    VGGPerceptualLoss,
    build_perceptual,
    candidate_assignment_loss,
    candidate_spacing_loss,
    flip_consistency_loss,
    list_perceptual_losses,
    mse_per_sample,
    uniform_pose_prior,
    view_equivariance_loss,
)
from unicorn.objectives.perceptual import (
    VGG16_URL,
    VGGWeightsError,
    VGGWeightsNotFoundError,
    load_vgg16_weights,
    vgg16_cache_path,
)

TETRA_VERTS = torch.tensor([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])
TETRA_FACES = torch.tensor([[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]])
OCTA_VERTS = torch.tensor([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
OCTA_FACES = torch.tensor([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def torchvision_vgg16_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """Random tensors under torchvision's vgg16 key names and shapes (features 0..28, classifier)."""
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"]
    g = torch.Generator().manual_seed(seed)
    state, cin, idx = {}, 3, 0
    for v in cfg:
        if v == "M":
            idx += 1
            continue
        state[f"features.{idx}.weight"] = torch.randn(v, cin, 3, 3, generator=g) * math.sqrt(2 / (9 * cin))
        state[f"features.{idx}.bias"] = torch.randn(v, generator=g) * 0.01
        cin, idx = v, idx + 2
    for i, (o, n) in {0: (4096, 25088), 3: (4096, 4096), 6: (1000, 4096)}.items():
        state[f"classifier.{i}.weight"] = torch.zeros(o, n)
        state[f"classifier.{i}.bias"] = torch.zeros(o)
    return state


def test_mse_per_sample():
    rec = torch.zeros(2, 1, 2, 2)
    target = torch.tensor([[[[1.0, 1.0], [1.0, 1.0]]], [[[2.0, 0.0], [0.0, 0.0]]]])
    assert torch.allclose(mse_per_sample(rec, target), torch.tensor([1.0, 1.0]))
    with pytest.raises(ValueError, match=r"rec and target differ in shape: \(2, 1, 2, 2\) vs \(1, 1, 2, 2\)"):
        mse_per_sample(rec, target[:1])


def test_uniform_pose_prior():
    probs = torch.tensor([[1.0, 0.5], [0.0, 0.5]])  # (K=2, B=2): mean p = (0.75, 0.25)
    assert math.isclose(float(uniform_pose_prior(probs)), 0.5)
    assert math.isclose(float(uniform_pose_prior(probs, "mean")), 0.25)
    assert float(uniform_pose_prior(torch.full((6, 3), 1 / 6))) < 1e-7


def test_normal_consistency_hand_values():
    # dihedral angles: tetrahedron normals at cos = -1/3 -> 4/3; octahedron cos = 1/3 -> 2/3
    loss = NormalConsistencyLoss(TETRA_FACES)
    assert loss.edges.shape == (6, 2)
    assert math.isclose(float(loss(TETRA_VERTS[None])), 4 / 3, rel_tol=1e-5)
    octa = NormalConsistencyLoss(OCTA_FACES)
    batch = torch.stack([OCTA_VERTS, OCTA_VERTS * torch.tensor([2.0, 1.0, 1.0])])
    single = float(octa(batch[1:]))
    assert math.isclose(float(octa(OCTA_VERTS[None])), 2 / 3, rel_tol=1e-5)
    assert math.isclose(float(octa(batch)), (2 / 3 + single) / 2, rel_tol=1e-5)
    t = TemplateMesh(level=3)
    sphere = float(NormalConsistencyLoss(t.faces)(t.verts[None] / t.verts.norm(dim=-1, keepdim=True)))
    assert 0 < sphere < 0.01
    with pytest.raises(ValueError, match="closed manifold"):
        NormalConsistencyLoss(TETRA_FACES[:3])


def test_candidate_assignment_loss_hand_values_and_gradient():
    logits = torch.tensor([[2.0, 0.0], [0.0, -20.0], [-1.0, 1.0]], requires_grad=True)  # (K=3, B=2)
    losses = torch.tensor([[0.3, 0.1], [0.2, 0.05], [0.4, 0.2]])  # best: candidate 1 for both samples
    log_probs = torch.log_softmax(logits, dim=0)
    value = candidate_assignment_loss(log_probs, losses)
    p = torch.softmax(logits.detach(), dim=0)
    assert math.isclose(float(value.detach()), -0.5 * float(p[1, 0].log() + p[1, 1].log()), rel_tol=1e-6)
    value.backward()
    # softmax cross-entropy: d/dlogit_k = (p_k - [k == best]) / B, not ~0 for the unlikely best candidate
    target = torch.zeros(3, 2)
    target[1] = 1.0
    assert torch.allclose(logits.grad, (p - target) / 2, atol=1e-7)
    assert float(logits.grad[1, 1]) < -0.49
    with pytest.raises(ValueError, match="shape"):
        candidate_assignment_loss(log_probs, losses[:, :1])


def test_candidate_spacing_loss_against_azimuth_differences():
    # candidates that differ in azimuth only: their geodesic angle is the azimuth difference on the circle
    azim = torch.tensor([[0.0, 10.0], [50.0, 350.0], [52.0, 200.0], [144.0, 90.0]], requires_grad=True)  # (K=4, B=2)
    zeros = torch.zeros_like(azim)
    R = azim_elev_roll_to_rotation(azim, zeros + 10.0, zeros)
    value = candidate_spacing_loss(R, min_angle=30.0)
    expected = 0.0
    for b in range(2):
        for k in range(4):
            for l in range(k + 1, 4):
                d = abs(float(azim[k, b].detach() - azim[l, b].detach())) % 360
                expected += max(0.0, 1 - min(d, 360 - d) / 30.0) / 2  # mean over the 2 images
    assert math.isclose(expected, (28 / 30 + 10 / 30) / 2)
    assert math.isclose(float(value.detach()), expected, rel_tol=1e-5)
    value.backward()
    # the near pairs (50 and 52; 10 and 350) pushed apart at 1 / 30 per degree, halved by the mean over images
    push = torch.zeros(4, 2)
    push[1, 0], push[2, 0], push[0, 1], push[1, 1] = 1, -1, -1, 1
    assert torch.allclose(azim.grad, push / 60, atol=1e-4)
    with pytest.raises(ValueError, match="min_angle"):
        candidate_spacing_loss(R, min_angle=0.0)
    with pytest.raises(ValueError, match="shape"):
        candidate_spacing_loss(R[0], min_angle=30.0)


def test_uniform_laplacian_hand_values():
    loss = UniformLaplacianLoss(OCTA_FACES)
    assert (loss.weights.sum(1) - 1).abs().max() < 1e-6  # 4 neighbours each, weight 1/4
    # every vertex +-e_i has the 4 others of the other axes as neighbours: mean 0, so |Lv| = |v|
    assert math.isclose(float(loss(OCTA_VERTS[None])), 1.0, rel_tol=1e-6)
    # L2 norm, not squared: scaling by 2 doubles it; batch mean
    assert math.isclose(float(loss(torch.stack([OCTA_VERTS, 2 * OCTA_VERTS]))), 1.5, rel_tol=1e-6)
    verts = OCTA_VERTS.clone()
    verts[0, 0] = 3.0  # only vertex 0's own term and its 4 neighbours' terms change
    # vertex 0: neighbours average 0 -> 3; e.g. (0,1,0): neighbours average (0.5,0,0) -> sqrt(1.25); vertex 1: 1
    expected = (3.0 + 4 * math.sqrt(1.25) + 1.0) / 6
    assert math.isclose(float(loss(verts[None])), expected, rel_tol=1e-5)
    v = OCTA_VERTS[None].clone().requires_grad_(True)
    loss(v).backward()
    assert torch.isfinite(v.grad).all()


def _one_line_with_options(message: str) -> bool:
    return "\n" not in message and all(
        key in message for key in ("paths.vgg16", "UNICORN_VGG16", "model.loss.perceptual=structural")
    )


def test_missing_vgg_file_error(tmp_path):
    path = tmp_path / "nowhere" / "vgg16-397923af.pth"
    with pytest.raises(VGGWeightsNotFoundError) as err:
        VGGPerceptualLoss(path)
    message = str(err.value)
    assert isinstance(err.value, UserError) and isinstance(err.value, FileNotFoundError)
    assert str(path) in message and "vgg16-397923af.pth" in message and "download.pytorch.org" in message
    assert _one_line_with_options(message)


def test_a_vgg_file_that_is_not_torchvisions_vgg16_is_one_line_naming_it(tmp_path, monkeypatch):
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"<html>404 Not Found</html>")  # a failed download saved under the weights' name
    not_a_dict, wrong_keys, wrong_shape = tmp_path / "tensor.pth", tmp_path / "resnet.pth", tmp_path / "shape.pth"
    torch.save(torch.zeros(3), not_a_dict)
    torch.save({"conv1.weight": torch.zeros(64, 3, 7, 7)}, wrong_keys)
    torch.save({**torchvision_vgg16_state(), "features.0.bias": torch.zeros(3)}, wrong_shape)
    deflated = deflated_torch_file(torchvision_vgg16_state(), tmp_path / "deflated.pth")
    for path, message in [
        (garbage, r"cannot read the VGG16 weights \S+garbage.pth: it is not a file written by torch.save$"),
        (deflated, r"cannot read the VGG16 weights \S+deflated.pth: its entry '\S+' is compressed"),
        (not_a_dict, r"the VGG16 weights \S+tensor.pth hold Tensor, not a state dict$"),
        (wrong_keys, r"^the VGG16 weights \S+resnet.pth: VGG16 state dict lacks 'features.0.weight' \(is it torchvis"),
        (wrong_shape, r"^the VGG16 weights \S+shape.pth: VGG16 state dict: 'features.0.bias' is \(3,\), expected"),
    ]:
        with pytest.raises(VGGWeightsError, match=message) as err:
            VGGPerceptualLoss(path)
        assert isinstance(err.value, UserError) and "\n" not in str(err.value)


@pytest.fixture
def torch_home(tmp_path, monkeypatch):
    """An empty torch hub cache (as torchvision uses it) under tmp_path."""
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))
    monkeypatch.setattr(torch.hub, "_hub_dir", None)
    return tmp_path / "torch" / "hub" / "checkpoints"


def test_offline_machine_without_cached_vgg_gets_one_line(torch_home, monkeypatch):
    def offline(url, dst, hash_prefix=None, progress=True):
        raise urllib.error.URLError("Name or service not known")

    monkeypatch.setattr(torch.hub, "download_url_to_file", offline)
    with pytest.raises(VGGWeightsNotFoundError) as err:
        load_vgg16_weights(None)
    message = str(err.value)
    assert _one_line_with_options(message) and "could not be downloaded" in message
    assert str(torch_home) in message  # says where the cache is
    with pytest.raises(VGGWeightsNotFoundError, match="no .*vgg16-397923af.pth"):
        load_vgg16_weights(None, download=False)


def test_vgg_weights_come_from_torch_hub_cache(torch_home, monkeypatch):
    """No path: torchvision's URL is fetched into torch's hub cache (hash prefix passed on), then reused."""
    state = torchvision_vgg16_state()
    calls = []

    def fake_download(url, dst, hash_prefix=None, progress=True):
        calls.append((url, hash_prefix))
        torch.save(state, dst)

    monkeypatch.setattr(torch.hub, "download_url_to_file", fake_download)
    loaded = load_vgg16_weights(None)
    assert calls == [(VGG16_URL, "397923af")]
    assert (torch_home / "vgg16-397923af.pth").is_file() and vgg16_cache_path() == torch_home / "vgg16-397923af.pth"
    assert torch.equal(loaded["features.14.weight"], state["features.14.weight"])
    loss = VGGPerceptualLoss(None)  # from the cache now: no second download
    assert len(calls) == 1 and torch.equal(loss.vgg.features[0].weight, state["features.0.weight"])
    # a file in the cache is checked as a file named by paths.vgg16 is (its hash was checked only when downloaded)
    deflated_torch_file(state, vgg16_cache_path())
    with pytest.raises(VGGWeightsError, match=r"cannot read the VGG16 weights \S+vgg16-397923af.pth: its entry"):
        VGGPerceptualLoss(None)
    assert len(calls) == 1


def test_vgg_perceptual_from_file_matches_hand_computation(tmp_path):
    state = torchvision_vgg16_state()
    path = tmp_path / "vgg16-397923af.pth"
    torch.save(state, path)
    loss = VGGPerceptualLoss(path)
    assert list(loss.parameters()) == [] and loss.state_dict() == {}
    g = torch.Generator().manual_seed(0)
    rec = torch.rand(2, 3, 16, 16, generator=g).requires_grad_(True)
    target = torch.rand(2, 3, 16, 16, generator=g)
    value = loss(rec, target)
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)

    def features(x):
        x = (x - mean) / std
        for i in (0, 2, "M", 5, 7, "M", 10, 12, 14):
            if i == "M":
                x = F.max_pool2d(x, 2)
            else:
                x = F.relu(F.conv2d(x, state[f"features.{i}.weight"], state[f"features.{i}.bias"], padding=1))
        return x / (x.norm(dim=1, keepdim=True) + 1e-10)

    expected = (features(rec.detach()) - features(target)).pow(2).flatten(1).mean(1)
    assert value.shape == (2,) and torch.allclose(value, expected, rtol=1e-4, atol=1e-7)
    assert float(loss(target, target).abs().max()) < 1e-10
    value.sum().backward()
    assert rec.grad.abs().sum() > 0
    with pytest.raises(VGGWeightsError, match="features.14.weight"):
        VGGPerceptualLoss({k: v for k, v in state.items() if k != "features.14.weight"})


def test_structural_loss():
    loss = StructuralLoss()
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(2, 3, 32, 32, generator=g), torch.rand(2, 3, 32, 32, generator=g)
    assert loss(a, a).abs().max() < 1e-5
    value = loss(a, b)
    assert value.shape == (2,) and (value > 0.1).all()
    assert float(loss(a, (a + 0.02).clamp(0, 1)).max()) < float(value.min())


def test_perceptual_registry():
    assert list_perceptual_losses() == ["structural", "vgg"]
    assert isinstance(build_perceptual("structural", vgg_weights="/unused"), StructuralLoss)
    assert build_perceptual(None) is None
    with pytest.raises(ValueError, match=r"unknown perceptual loss 'lpips'; known: \['structural', 'vgg'\]"):
        build_perceptual("lpips")


def test_reconstruction_and_mesh_terms_are_the_weighted_losses():
    """Each term against its own weight times the unweighted loss (MSE, structural, normal, Laplacian)."""
    g = torch.Generator().manual_seed(0)
    rec, target = torch.rand(2, 2, 3, 16, 16, generator=g)
    structural = StructuralLoss()
    terms = ReconstructionLoss(0.5, structural, 2.0)(rec, target)
    torch.testing.assert_close(terms["rgb"], 0.5 * ((rec - target) ** 2).mean((1, 2, 3)))
    torch.testing.assert_close(terms["perceptual"], 2.0 * structural(rec, target))
    assert list(ReconstructionLoss(0.0, structural, 1.0)(rec, target)) == ["perceptual"]  # weight 0: left out
    assert list(ReconstructionLoss(1.0, structural, 0.0)(rec, target)) == ["rgb"]
    verts, faces = ellipsoid(1, (1.0, 0.7, 0.7), 0.6)
    bumpy = (verts * (1 + 0.1 * torch.rand(verts.shape, generator=g))).unsqueeze(0)
    # distinct non-zero weights: each term must carry its own weight
    regularizer = MeshRegularizer(faces, verts.shape[0], 0.1, 0.3)
    normal = NormalConsistencyLoss(faces)(bumpy, reduction="none")
    laplacian = UniformLaplacianLoss(faces, verts.shape[0])(bumpy, reduction="none")
    assert float(normal.min()) > 0 and float(laplacian.min()) > 0
    mesh = regularizer(bumpy, reduction="none")
    assert list(mesh) == ["normal", "laplacian"]
    torch.testing.assert_close(mesh["normal"], 0.1 * normal)
    torch.testing.assert_close(mesh["laplacian"], 0.3 * laplacian)
    mean = regularizer(bumpy)
    torch.testing.assert_close(mean["normal"], 0.1 * normal.mean())
    torch.testing.assert_close(mean["laplacian"], 0.3 * laplacian.mean())
    # weight 0: left out
    assert list(MeshRegularizer(faces, verts.shape[0], 0.1, 0.0)(bumpy)) == ["normal"]
    assert list(MeshRegularizer(faces, verts.shape[0], 0.0, 0.3)(bumpy)) == ["laplacian"]


def _candidates(R, T, logits):
    log_probs = torch.log_softmax(logits, 0)
    return PoseOutput(angles=torch.zeros(*R.shape[:2], 3), R=R, T=T, probs=log_probs.exp(), log_probs=log_probs)


def test_flip_consistency_is_zero_for_mirrored_candidates_and_grows_with_the_difference():
    g = torch.Generator().manual_seed(0)
    K, B = 4, 3
    mirror = torch.tensor([2, 1, 0, 3])
    angles = torch.rand(K, B, 3, generator=g) * 60
    R = azim_elev_roll_to_rotation(angles[..., 0], angles[..., 1], angles[..., 2])
    T, logits = torch.rand(K, B, 3, generator=g), torch.randn(K, B, generator=g)
    R_m, T_m = mirrored_pose(R, T)
    poses = _candidates(R, T, logits)
    # the flipped image's candidate mirror[k] is candidate k's mirror (mirror is an involution)
    consistent = _candidates(R_m[mirror], T_m[mirror], logits[mirror])
    assert float(flip_consistency_loss(poses, consistent, mirror)) == pytest.approx(0.0, abs=1e-6)
    # a naive sum of the four parts
    other = _candidates(R, T + 0.1, logits.flip(0))
    p, q = poses.probs, other.probs[mirror]
    kl = (p * (p.log() - q.log())).sum(0).mean() + (q * (q.log() - p.log())).sum(0).mean()
    geometry = sum(
        float(((other.R[mirror[k], b] - R_m[k, b]) ** 2).sum() + ((other.T[mirror[k], b] - T_m[k, b]) ** 2).sum())
        for k in range(K)
        for b in range(B)
    ) / (K * B)
    assert float(flip_consistency_loss(poses, other, mirror)) == pytest.approx(geometry + float(kl), rel=1e-5)


def _equivariance_naive(poses, moved, roll, shift, head, focal):
    """view_equivariance_loss one candidate and one image at a time."""
    K, B = poses.probs.shape
    total = 0.0
    for k in range(K):
        for b in range(B):
            a = poses.angles[k, b].tolist()
            target = [a[0], a[1], a[2] + float(roll[b])]
            for i in range(3):
                if float(head.R_range[i]) == 0:
                    continue
                lo = float(head.R_init[k, i] - head.R_range[i])
                hi = float(head.R_init[k, i] + head.R_range[i])
                clamped = min(max(target[i], lo), hi)
                total += ((float(moved.angles[k, b, i]) - clamped) / float(head.R_range[i])) ** 2 / (K * B)
            tx, ty, tz = poses.T[k, b].tolist()
            r = math.radians(float(roll[b]))
            t_target = [
                math.cos(r) * tx - math.sin(r) * ty + float(shift[b, 0]) * tz / focal,
                math.sin(r) * tx + math.cos(r) * ty + float(shift[b, 1]) * tz / focal,
                tz,
            ]
            for j in range(3):
                rng = float(head.T_range[j])
                if rng > 0:
                    lo, hi = float(head.T_init[j]) - rng, float(head.T_init[j]) + rng
                    clamped = min(max(t_target[j], lo), hi)
                    total += ((float(moved.T[k, b, j]) - clamped) / rng) ** 2 / (K * B)
    p, q = poses.probs, moved.probs
    return total + float((p * (p.log() - q.log())).sum(0).mean())


@pytest.mark.parametrize(
    "ranges",
    [{"T_range": (0.3, 0.3, 0.2)}, {"elev_range": (10, 10), "roll_range": (0, 0), "T_range": (0.2, 0.2, 0)}],
    ids=["real", "fixed elevation"],
)
def test_view_equivariance_against_a_naive_loop_and_zero_when_the_candidates_follow(ranges):
    head = PoseHead(in_features=8, **ranges)
    g = torch.Generator().manual_seed(0)
    K, B, focal = head.n_candidates, 3, 3.7
    poses = head._compose(
        torch.rand(K, B, 3, generator=g) - 0.5,
        torch.rand(K, B, 3, generator=g) - 0.5,
        torch.log_softmax(torch.randn(K, B, generator=g), 0),
    )
    roll, shift = torch.tensor([10.0, -5.0, 0.0]), torch.tensor([[0.05, 0.0], [-0.02, 0.04], [0.0, 0.0]])
    # the candidates of the moved images, each followed exactly (within the head's reach)
    angles = poses.angles + torch.stack([torch.zeros(B), torch.zeros(B), roll], -1)
    r = torch.deg2rad(roll)
    T = poses.T
    x = r.cos() * T[..., 0] - r.sin() * T[..., 1] + shift[:, 0] * T[..., 2] / focal
    y = r.sin() * T[..., 0] + r.cos() * T[..., 1] + shift[:, 1] * T[..., 2] / focal
    followed = PoseOutput(angles, poses.R, torch.stack([x, y, T[..., 2]], -1), poses.probs, poses.log_probs)
    assert float(view_equivariance_loss(poses, followed, roll, shift, head, focal)) == pytest.approx(0.0, abs=1e-10)
    # the candidates of a branch that reads its azimuth from the roll, with other probabilities
    turned = PoseOutput(
        poses.angles + torch.stack([roll, torch.zeros(B), torch.zeros(B)], -1),
        poses.R,
        poses.T + 0.02,
        *(lambda lp: (lp.exp(), lp))(torch.log_softmax(torch.randn(K, B, generator=g), 0)),
    )
    loss = view_equivariance_loss(poses, turned, roll, shift, head, focal)
    assert float(loss) > 0.05
    assert float(loss) == pytest.approx(_equivariance_naive(poses, turned, roll, shift, head, focal), rel=1e-5)


def test_view_equivariance_leaves_out_what_the_head_holds_and_trains_the_moved_branch_only():
    head = PoseHead(in_features=8)
    K, B = head.n_candidates, 2
    poses = head._compose(torch.zeros(K, B, 3), torch.zeros(K, B, 3), torch.full((K, B), -math.log(K)))
    roll, shift = torch.tensor([10.0, -10.0]), torch.tensor([[0.1, 0.0], [0.0, 0.1]])
    # a branch that ignores the roll and the shift
    still = PoseOutput(
        poses.angles.clone().requires_grad_(), poses.R, poses.T.clone().requires_grad_(), poses.probs, poses.log_probs
    )
    loss = view_equivariance_loss(poses, still, roll, shift, head, 3.7)
    assert float(loss) > 0
    loss.backward()
    assert still.angles.grad[..., 2].abs().sum() > 0 and still.angles.grad[..., :2].abs().sum() == 0
    assert still.T.grad[..., :2].abs().sum() > 0
    head.use_elevation_roll.fill_(False)
    head.use_translation.fill_(False)
    assert float(view_equivariance_loss(poses, still, roll, shift, head, 3.7)) == pytest.approx(0.0, abs=1e-12)
