"""Building blocks: template, MLPs, masks, field, generators, encoder, pose and scale heads."""

from __future__ import annotations

import copy
import math

import pytest
import torch

from tests.support.checkpoints import torchvision_resnet18_shapes
from unicorn.geometry.mesh import ellipsoid
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.model import (
    MLP,
    DeformationField,
    GiraffeGenerator,
    PoseHead,
    ProgressiveMask,
    ResNet18,
    ScaleHead,
    ShapeHead,
    TemplateMesh,
    active_dims_at,
)
from unicorn.model.pose import mirrored_pose
from unicorn.render import TexturesVertex, build_renderer


def random_state(shapes: dict[str, tuple[int, ...]]) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(0)
    return {
        k: (torch.tensor(7) if k.endswith("num_batches_tracked") else torch.rand(s, generator=g))
        for k, s in shapes.items()
    }


def test_template_sizes_axes_and_uvs():
    t = TemplateMesh(level=3, scale=0.6)
    assert t.verts.shape == (642, 3) and t.faces.shape == (1280, 3)
    assert torch.allclose(t.verts.abs().amax(0), torch.tensor([0.6, 0.42, 0.42]), atol=1e-5)
    assert t.face_uvs.shape == (1280, 3, 2) and t.wrap_u
    u = t.face_uvs[..., 0]
    assert (u.amax(1) - u.amin(1)).max() < 0.5  # the seam is fixed: no face spans the whole texture
    assert t.face_uvs[..., 1].min() >= 0 and t.face_uvs[..., 1].max() <= 1
    ref = TemplateMesh(level=3, uv_mode="reference")
    assert not ref.wrap_u and torch.equal(ref.face_uvs, ref.vertex_uvs[ref.faces])
    assert TemplateMesh(level=4).num_verts == 2562
    assert t.state_dict() == {}  # derived from the configuration
    with pytest.raises(ValueError, match="uv_mode"):
        TemplateMesh(uv_mode="bad")


def test_mlp_layout_and_zero_init():
    mlp = MLP(512, 7, 128, 3, zero_last=True)
    assert [k for k in mlp.state_dict() if k.endswith("weight")] == ["0.weight", "2.weight", "4.weight", "6.weight"]
    assert torch.equal(mlp(torch.randn(4, 512)), torch.zeros(4, 7))
    assert MLP(512, 7).forward(torch.randn(4, 512)).abs().sum() > 0


def test_active_dims_schedule():
    assert [active_dims_at(s, [2, 8, 32], [10, 20, 30]) for s in (0, 10, 25, 30, 99)] == [0, 2, 8, 32, 32]
    assert active_dims_at(0, [2, 8], [0, 5]) == 2


def test_mask_switches_dims_off_and_is_saved():
    mask = ProgressiveMask(6, active_dims=2)
    code = torch.arange(1.0, 13.0).view(2, 6)
    out = mask(code)
    assert torch.equal(out[:, :2], code[:, :2]) and out[:, 2:].abs().sum() == 0
    mask.set_active_dims(0)
    assert mask(code).abs().sum() == 0
    mask.set_active_dims(6)
    assert torch.equal(mask(code), code)
    assert int(mask.state_dict()["active"]) == 6
    mask.set_active_dims(4.0)  # a whole float is a count
    assert mask.active_dims == 4 and int(mask.state_dict()["active"]) == 4
    for bad in (7, -1, 2.5, True):
        with pytest.raises(ValueError, match=rf"^active dims must be a whole number in \[0, 6\], got {bad!r}$"):
            mask.set_active_dims(bad)
    assert mask.active_dims == 4


def test_deformation_field_zero_init_and_shapes():
    field = DeformationField(code_dim=8, n_units=32)
    pts = torch.randn(10, 3)
    out = field(pts, torch.randn(4, 8))
    assert out.shape == (4, 10, 3) and out.abs().sum() == 0
    head = ShapeHead(512, code_dim=8, n_field_units=32)
    assert head.code(torch.randn(3, 512)).shape == (3, 8)
    assert int(head.mask.active) == 0
    with pytest.raises(ValueError, match="code"):
        field(pts, torch.randn(4, 7))


def test_symmetric_shape_head_is_the_mean_of_the_field_and_its_mirror():
    torch.manual_seed(0)
    head = ShapeHead(512, code_dim=8, n_field_units=32, symmetric=True)
    for p in head.field.parameters():  # the field starts at zero: give it something to mirror
        torch.nn.init.normal_(p, std=0.3)
    template, code = torch.randn(10, 3), torch.randn(4, 8)
    flip = torch.tensor([1.0, 1.0, -1.0])  # the mirror through z = 0, written out
    expected = (head.field(template, code) + head.field(template * flip, code) * flip) / 2
    delta = head(template, code)
    assert delta.shape == (4, 10, 3) and delta.abs().amax() > 1e-3
    torch.testing.assert_close(delta, expected)
    # a template symmetric in z keeps its symmetry: the mirror point's displacement is the mirrored displacement
    pair = torch.cat([template, template * flip])
    both = head(pair, code)
    torch.testing.assert_close(both[:, 10:], both[:, :10] * flip)


@pytest.mark.parametrize(
    ("code_dim", "min_features", "widths"),
    [(128, 16, [64, 32, 16, 16, 16, 16]), (512, 64, [256, 128, 64, 64, 64, 64]), (256, 64, [128, 64, 64, 64, 64, 64])],
)
def test_giraffe_generator_widths(code_dim, min_features, widths):
    gen = GiraffeGenerator(code_dim, 64, min_features)
    assert [c.out_channels for c in gen.conv_layers] == widths
    assert [c.in_channels for c in gen.conv_rgb] == [code_dim, *widths]
    assert all(c.bias is None for c in [*gen.conv_layers, *gen.conv_rgb])


def test_generator_range_and_zero_code_grey():
    gen = GiraffeGenerator(32, 16, 8)
    out = gen(torch.randn(2, 32) * 5)
    assert out.shape == (2, 3, 16, 16) and out.min() >= 0 and out.max() <= 1
    assert torch.allclose(gen(torch.zeros(1, 32)), torch.full((1, 3, 16, 16), 0.5))
    with pytest.raises(ValueError, match="power of 2"):
        GiraffeGenerator(32, 48)


def test_resnet18_loads_torchvision_state_dict():
    enc = ResNet18()
    shapes = torchvision_resnet18_shapes()
    ours = {k: tuple(v.shape) for k, v in enc.state_dict().items()}
    assert ours == {k: s for k, s in shapes.items() if not k.startswith("fc.")}
    state = random_state(shapes)
    enc.load_torchvision_state_dict(state)
    assert torch.equal(enc.layer3[0].downsample[0].weight, state["layer3.0.downsample.0.weight"])
    assert enc(torch.rand(2, 3, 64, 64)).shape == (2, 512)
    with pytest.raises(RuntimeError):
        enc.load_torchvision_state_dict({k: v for k, v in state.items() if k != "conv1.weight"})


@pytest.mark.parametrize("width", [16, 32])
def test_narrow_resnet18_scales_every_channel_count(width):
    # torchvision's layout with every channel count (a multiple of 64; kernel sizes and the 3 input channels are
    # not) scaled by width / 64
    expected = {
        k: tuple(d * width // 64 if d % 64 == 0 else d for d in shape)
        for k, shape in torchvision_resnet18_shapes().items()
        if not k.startswith("fc.")
    }
    enc = ResNet18(width)
    assert {k: tuple(v.shape) for k, v in enc.state_dict().items()} == expected
    assert enc.out_features == 8 * width
    assert enc(torch.rand(3, 3, 32, 32)).shape == (3, 8 * width)
    with pytest.raises(ValueError, match="encoder width"):
        ResNet18(0)


@pytest.mark.parametrize("pooled", [["layer3", "layer4"], ["layer4", "layer1"], ["layer2"]])
def test_resnet18_pools_the_named_stages_side_by_side(pooled):
    torch.manual_seed(0)
    enc = ResNet18(8, pooled=pooled).eval()
    x = torch.rand(2, 3, 32, 32)
    # the stages run one after the other by hand, each output averaged over its map
    h = enc.maxpool(enc.relu(enc.bn1(enc.conv1(x))))
    means = {}
    for name in ("layer1", "layer2", "layer3", "layer4"):
        h = getattr(enc, name)(h)
        means[name] = h.mean((2, 3))
    order = [name for name in ("layer1", "layer2", "layer3", "layer4") if name in pooled]
    expected = torch.cat([means[name] for name in order], 1)
    channels = {"layer1": 8, "layer2": 16, "layer3": 32, "layer4": 64}
    assert enc.out_features == expected.shape[1] == sum(channels[name] for name in pooled)
    torch.testing.assert_close(enc(x), expected)
    # the same weights give the paper's features (the last stage's) by default
    default = ResNet18(8).eval()
    default.load_state_dict(enc.state_dict())
    torch.testing.assert_close(default(x), means["layer4"])


@pytest.mark.parametrize("pooled", [[], ["layer5"], ["layer3", "layer3"]])
def test_resnet18_pooled_stages_are_checked(pooled):
    with pytest.raises(ValueError, match="pooled stages must be distinct names"):
        ResNet18(8, pooled=pooled)


def test_pose_anchors_zero_init():
    head = PoseHead(16, n_units=8)
    assert torch.allclose(head.R_init[:, 0], torch.tensor([0.0, 60, 120, 180, 240, 300]))
    assert torch.allclose(head.R_init[:, 1:], torch.tensor([10.0, 0.0]).expand(6, 2))
    assert torch.allclose(head.R_range, torch.tensor([31.2, 20.8, 31.2]))
    out = head(torch.randn(5, 16))
    assert out.R.shape == (6, 5, 3, 3) and out.T.shape == (6, 5, 3) and out.probs.shape == (6, 5)
    assert torch.allclose(out.probs.sum(0), torch.ones(5))
    anchors = azim_elev_roll_to_rotation(head.R_init[:, 0], head.R_init[:, 1], head.R_init[:, 2])
    assert torch.allclose(out.R, anchors.unsqueeze(1).expand(6, 5, 3, 3), atol=1e-6)
    assert torch.allclose(out.T, torch.tensor([0.0, 0.0, 2.732]).expand(6, 5, 3))
    R, T = out.select()
    assert R.shape == (5, 3, 3) and torch.equal(R[0], out.R[out.best[0], 0])
    assert out.flat()[0].shape == (30, 3, 3) and torch.equal(out.flat()[0][5 + 2], out.R[1, 2])


def test_pose_offsets_are_bounded_and_translation_switch():
    head = PoseHead(16, T_range=(0.2, 0.2, 0.0), n_units=8)
    with torch.no_grad():
        for mlp in [*head.rot_regressors, *head.T_regressors]:
            mlp[-1].bias.fill_(100.0)  # saturate tanh
    out = head(torch.randn(3, 16))
    assert torch.allclose(out.angles, (head.R_init + head.R_range).unsqueeze(1).expand(6, 3, 3), atol=1e-4)
    assert torch.allclose(out.T[..., :2], torch.full((6, 3, 2), 0.2)) and torch.allclose(
        out.T[..., 2], torch.tensor(2.732)
    )
    head.use_translation.fill_(False)
    assert torch.allclose(head(torch.randn(3, 16)).T, torch.tensor([0.0, 0.0, 2.732]).expand(6, 3, 3))
    assert "use_translation" in head.state_dict()


def test_pose_elevation_roll_switch_holds_them_at_the_anchors():
    head = PoseHead(16, elev_range=(-10, 30), roll_range=(-30, 30), n_units=8)
    with torch.no_grad():
        for mlp in head.rot_regressors:
            mlp[-1].bias.fill_(100.0)  # saturate tanh: every offset at its bound
    features = torch.randn(3, 16)
    free = head(features).angles
    head.use_elevation_roll.fill_(False)
    held = head(features).angles
    anchors = head.R_init.unsqueeze(1).expand(6, 3, 3)
    assert torch.allclose(free, (head.R_init + head.R_range).unsqueeze(1).expand(6, 3, 3), atol=1e-4)
    assert torch.equal(held[..., 0], free[..., 0]) and torch.equal(held[..., 1:], anchors[..., 1:])
    assert torch.equal(head.R_init[:, 1:], torch.tensor([10.0, 0.0]).expand(6, 2))  # the middle of the ranges
    # held off, the elevation and roll outputs get no gradient; the azimuth's does
    with torch.no_grad():
        for mlp in head.rot_regressors:
            mlp[-1].bias.zero_()  # away from saturation
    head(features).angles.sum().backward()
    grad = head.rot_regressors[0][-1].weight.grad
    assert grad[1:].abs().sum() == 0 and grad[0].abs().sum() > 0
    # set by the stage callback every iteration, so checkpoints written without it still load
    assert "use_elevation_roll" not in head.state_dict()
    head.load_state_dict(PoseHead(16, n_units=8).state_dict())


def test_pose_shapenet_ranges_fix_elevation_and_roll():
    head = PoseHead(16, elev_range=(30, 30), roll_range=(0, 0), n_units=8)
    assert torch.allclose(head.R_init[:, 1:], torch.tensor([30.0, 0.0]).expand(6, 2))
    assert head.R_range[1] == 0 and head.R_range[2] == 0
    single = PoseHead(16, n_azim=1, azim_range=(-90, 90), n_units=8)
    assert single.R_init[0, 0] == 0 and math.isclose(float(single.R_range[0]), 90.0)


def test_scale_identity_at_init_and_bounded():
    head = ScaleHead(16, scale_range=0.3, n_units=8)
    assert torch.equal(head(torch.randn(4, 16)), torch.ones(4, 3))
    with torch.no_grad():
        head.regressor[-1].bias.fill_(-100.0)
    assert torch.allclose(head(torch.randn(4, 16)), torch.full((4, 3), 0.7))
    head.use_scale.fill_(False)
    assert torch.equal(head(torch.randn(4, 16)), torch.ones(4, 3))


@pytest.mark.parametrize(
    "size, kernel, stride, padding, kept",
    [
        (1, 3, 1, 1, (1, 1, 1, 1)),  # layer 4's second convolutions at 32 px: the centre tap
        (2, 3, 2, 1, (1, 1, 2, 2)),  # layer 4's first one: 2 x 2 in, one pixel out
        (1, 7, 2, 3, (3, 3, 1, 1)),
        (2, 3, 1, 1, None),  # 2 x 2 out
        (1, 1, 1, 0, None),  # nothing to crop
        (2, 1, 2, 0, None),
        (3, 3, 1, 0, None),
        (4, 7, 2, 3, None),
    ],
)
def test_encoder_conv_trains_only_the_taps_that_meet_the_image(size, kernel, stride, padding, kept):
    """After ``keep_taps_for(size)``: the output and the input and bias gradients are ``F.conv2d``'s with the
    whole kernel and its padding, the kept taps get that kernel gradient's values, and it is zero on every other
    tap (which is why they need not be trained)."""
    import torch.nn.functional as F

    from unicorn.model.encoder import Conv2d

    g = torch.Generator().manual_seed(0)
    conv = Conv2d(5, 4, kernel, stride=stride, padding=padding, bias=True).double()
    whole = conv.weight.detach().clone().requires_grad_()
    assert conv.keep_taps_for(size, size) == (kept is not None)
    assert conv.taps == kept
    x = torch.rand(3, 5, size, size, generator=g, dtype=torch.float64, requires_grad=True)
    ours = conv(x)
    ref = F.conv2d(x, whole, conv.bias, stride=stride, padding=padding)
    torch.testing.assert_close(ours, ref)
    upstream = torch.rand(ref.shape, generator=g, dtype=torch.float64)
    x_ours, w_ours, b_ours = torch.autograd.grad(ours, (x, conv.weight, conv.bias), upstream)
    x_ref, w_ref, b_ref = torch.autograd.grad(ref, (x, whole, conv.bias), upstream)
    torch.testing.assert_close(x_ours, x_ref)
    torch.testing.assert_close(b_ours, b_ref)
    if kept is None:
        torch.testing.assert_close(w_ours, w_ref)
        return
    top, left, h, w = kept
    assert conv.weight.shape == (4, 5, h, w)
    torch.testing.assert_close(w_ours, w_ref[:, :, top : top + h, left : left + w])
    w_ref[:, :, top : top + h, left : left + w] = 0
    assert w_ref.abs().max() == 0


def test_encoder_conv_with_kept_taps_saves_loads_and_runs_the_whole_kernel():
    import torch.nn.functional as F

    from unicorn.model.encoder import Conv2d

    conv = Conv2d(5, 4, 3, padding=1, bias=False)
    conv.keep_taps_for(1, 1)
    whole = torch.randn(4, 5, 3, 3)
    conv.load_state_dict({"weight": whole})  # a whole kernel loads into both parts
    assert torch.equal(conv.weight, whole[:, :, 1:2, 1:2])
    assert torch.equal(conv.state_dict()["weight"], whole)
    with torch.no_grad():  # training moves the kept taps only; the saved kernel shows them in place
        conv.weight.add_(1.0)
    expected = whole.clone()
    expected[:, :, 1, 1] += 1.0
    assert torch.equal(conv.state_dict()["weight"], expected)
    # other input sizes run the whole kernel with its padding, and the kept taps still learn
    x = torch.rand(2, 5, 4, 4, requires_grad=True)
    whole_now = expected.clone().requires_grad_()
    torch.testing.assert_close(conv(x), F.conv2d(x, whole_now, padding=1))
    (grad,) = torch.autograd.grad(conv(x).sum(), conv.weight)
    (grad_ref,) = torch.autograd.grad(F.conv2d(x, whole_now, padding=1).sum(), whole_now)
    torch.testing.assert_close(grad, grad_ref[:, :, 1:2, 1:2])
    conv.double()  # the untrained rest follows dtype and device changes
    assert conv.state_dict()["weight"].dtype == torch.float64
    with pytest.raises(RuntimeError, match="size mismatch"):
        conv.load_state_dict({"weight": torch.randn(4, 5, 2, 2)})
    with pytest.raises(RuntimeError, match="already"):
        conv.keep_taps_for(1, 1)


def test_resnet18_at_its_image_size_trains_like_the_whole_network():
    """ResNet-18 told its image size (32 px: layer 4 on 1 x 1 maps) has fewer parameters but the same state dict
    as the whole network, through Adam steps; and an older optimizer state (whole-kernel moments, as the whole
    network's Adam holds them) continues the same after :func:`crop_optimizer_state`."""
    from unicorn.model.encoder import Conv2d, crop_optimizer_state

    # float64: Adam's first steps turn float32 rounding of near-zero gradients into differences of ~lr
    torch.manual_seed(0)
    whole = ResNet18(8).double()
    torch.manual_seed(0)
    kept = ResNet18(8, image_size=32).double()
    cropped = [n for n, m in kept.named_modules() if isinstance(m, Conv2d) and m.taps is not None]
    assert cropped == ["layer4.0.conv1", "layer4.0.conv2", "layer4.1.conv1", "layer4.1.conv2"]
    assert sum(p.numel() for p in kept.parameters()) < 0.5 * sum(p.numel() for p in whole.parameters())
    assert all(torch.equal(v, kept.state_dict()[k]) for k, v in whole.state_dict().items())
    opt_whole = torch.optim.Adam(whole.parameters(), lr=1e-2)
    opt_kept = torch.optim.Adam(kept.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(1)
    batches = [torch.rand(4, 3, 32, 32, generator=g, dtype=torch.float64) for _ in range(4)]

    def step(net, opt, x):
        opt.zero_grad(set_to_none=True)
        net(x).square().mean().backward()
        opt.step()

    def assert_same_state(a, b):
        sa, sb = a.state_dict(), b.state_dict()
        assert sa.keys() == sb.keys()
        for k in sa:
            torch.testing.assert_close(sa[k], sb[k], msg=k)

    for x in batches[:3]:
        step(whole, opt_whole, x)
        step(kept, opt_kept, x)
    assert_same_state(whole, kept)
    older = copy.deepcopy(opt_whole.state_dict())  # as read from a checkpoint: no tensor shared with opt_whole
    assert crop_optimizer_state(kept, list(kept.parameters()), older) == 8  # two moments of four kernels
    resumed = torch.optim.Adam(kept.parameters(), lr=1e-2)
    resumed.load_state_dict(older)
    step(whole, opt_whole, batches[3])
    step(kept, resumed, batches[3])
    assert_same_state(whole, kept)
    # other image sizes run the whole network
    x64 = torch.rand(2, 3, 64, 64, generator=g, dtype=torch.float64)
    whole.eval(), kept.eval()
    torch.testing.assert_close(whole(x64), kept(x64))


@pytest.mark.parametrize("n_azim", [1, 4, 6, 12])
def test_mirror_index_pairs_each_anchor_with_its_mirror(n_azim):
    head = PoseHead(n_azim=n_azim, roll_range=(-15.0, 15.0))
    mirror = head.mirror_index()
    assert torch.equal(mirror[mirror], torch.arange(n_azim))  # an involution
    # anchors at a = 360 k / n: the mirror of a is 180 - a
    expected = [round(((180.0 - 360.0 * k / n_azim) % 360.0) * n_azim / 360.0) % n_azim for k in range(n_azim)]
    assert mirror.tolist() == expected


def test_a_flipped_render_is_the_render_at_the_mirrored_pose():
    """Against the horizontally flipped image: a mesh symmetric through z = 0 (but not through x = 0), coloured by
    x and y, shows at mirrored_pose(R, T) exactly the horizontal flip of what it shows at (R, T)."""
    verts, faces = ellipsoid(2, scale=0.6)
    verts = verts * torch.tensor([1.0, 0.7, 0.5])
    verts = verts + (verts[:, :1] > 0) * torch.tensor([0.3, 0.1, 0.0])  # a longer, higher front: no x symmetry
    colors = torch.stack([verts[:, 0].sigmoid(), verts[:, 1].sigmoid(), torch.full_like(verts[:, 0], 0.5)], 1)
    R = azim_elev_roll_to_rotation(torch.tensor([35.0, 250.0]), torch.tensor([20.0, -5.0]), torch.tensor([8.0, -3.0]))
    T = torch.tensor([[0.1, -0.05, 2.7], [-0.08, 0.02, 2.9]])
    renderer = build_renderer("hard", image_size=32)
    batch = (verts[None].repeat(2, 1, 1), faces, TexturesVertex(colors[None].repeat(2, 1, 1)))
    seen = renderer(*batch, R=R, T=T)
    R_m, T_m = mirrored_pose(R, T)
    mirrored = renderer(*batch, R=R_m, T=T_m)
    assert torch.allclose(mirrored, seen.flip(-1), atol=1e-4)
    assert not torch.allclose(seen, seen.flip(-1), atol=1e-2)  # the views are not symmetric themselves
