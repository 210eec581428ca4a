"""The structured autoencoder: outputs, zero init, masks, switches, detaching, both training steps."""

from __future__ import annotations

import pytest
import torch

from tests.support.model import IMAGE_SIZE, ellipsoid_images, randomize_heads, tiny_config
from unicorn.checks import ShapeError
from unicorn.geometry.rotations import azim_elev_roll_to_rotation
from unicorn.model import Unicorn, merge_config
from unicorn.objectives import Objectives, ReconstructionLoss

# randomised heads can fold meshes into more layers than faces_per_pixel: irrelevant here
pytestmark = pytest.mark.filterwarnings("ignore:some pixels had more than faces_per_pixel")


def grads_of(module: torch.nn.Module) -> float:
    return sum(float(p.grad.abs().sum()) for p in module.parameters() if p.grad is not None)


def test_config_validation():
    with pytest.raises(KeyError, match="unknown key"):
        merge_config({"shape": {"code_size": 3}})
    with pytest.raises(KeyError, match="unknown model config group"):
        merge_config({"shapes": {}})
    # the model holds no loss: the perceptual loss's weights are needed by the training losses only
    missing = merge_config(tiny_config(loss={"perceptual": "vgg", "vgg_weights": "/nonexistent/vgg16.pth"}))
    Unicorn(missing)
    with pytest.raises(FileNotFoundError, match="vgg16-397923af.pth"):
        ReconstructionLoss.from_config(missing["loss"])


def test_prediction_shapes_and_ranges(tiny_model, images):
    randomize_heads(tiny_model)
    pred = tiny_model.predict(images)
    B, K = images.shape[0], tiny_model.n_candidates
    assert pred.verts.shape == (B, 642, 3) and pred.canonical_verts.shape == (B, 642, 3)
    assert pred.shape_code.shape == (B, 32) and pred.texture_code.shape == (B, 128)
    assert pred.background_code.shape == (B, 128)
    assert pred.texture.shape == (B, 3, 16, 16) and 0 <= pred.texture.min() and pred.texture.max() <= 1
    assert pred.background.shape == (B, 3, IMAGE_SIZE, IMAGE_SIZE)
    assert 0 <= pred.background.min() and pred.background.max() <= 1
    assert pred.scale.shape == (B, 3) and ((pred.scale >= 0.7) & (pred.scale <= 1.3)).all()
    assert pred.poses.R.shape == (K, B, 3, 3) and pred.poses.probs.shape == (K, B)
    assert torch.allclose(pred.poses.probs.sum(0), torch.ones(B))
    eye = torch.eye(3).expand(B, 3, 3)
    assert torch.allclose(pred.R @ pred.R.transpose(1, 2), eye, atol=1e-5)
    lo, hi = tiny_model.pose.R_init - tiny_model.pose.R_range, tiny_model.pose.R_init + tiny_model.pose.R_range
    assert ((pred.poses.angles >= lo[:, None] - 1e-4) & (pred.poses.angles <= hi[:, None] + 1e-4)).all()
    assert ((pred.T - torch.tensor([0, 0, 2.732])).abs() <= 0.3 + 1e-6).all()
    rec, _ = tiny_model(images)
    assert rec.shape == images.shape and torch.isfinite(rec).all()


@pytest.mark.parametrize(
    ("dtype", "hint"),
    [
        (torch.uint8, r" \(pixels in \[0, 255\]: images.to\(torch.float32\) / 255, the model reads \[0, 1\]\)$"),
        (torch.bool, r" \(images.to\(torch.float32\) converts it: the model reads \[0, 1\]\)$"),
        (torch.float64, r" \(images.to\(torch.float32\) converts it\)$"),
    ],
    ids=str,
)
def test_images_of_another_dtype_are_refused_by_name(tiny_model, images, dtype, hint):
    with pytest.raises(TypeError, match=rf"images must be torch.float32, the model's dtype, got {dtype}{hint}"):
        tiny_model.predict((images > 0.5).to(dtype) if dtype == torch.bool else (images * 255).to(dtype))


@pytest.mark.parametrize(
    ("values", "message"),
    [
        (lambda x: x * 255, r"got values in \[.*, 25\d.*\] \(pixels in \[0, 255\]: divide by 255\)$"),
        (lambda x: (x - 0.45) / 0.225, r"got values in \[-2.*, 2.*\]$"),  # an ImageNet-style normalisation
        (lambda x: x.index_fill(1, torch.tensor([2]), float("nan")), "hold NaN or infinite values"),
    ],
    ids=["0-255", "normalised", "nan"],
)
def test_images_out_of_the_unit_range_are_refused(tiny_model, images, values, message):
    with pytest.raises(ValueError, match=message):
        tiny_model.predict(values(images))
    tiny_model.predict(images.clamp(0, 1) * (1 + 1e-4))  # a resampled image's rounding passes


@pytest.mark.parametrize("background", [True, False], ids=["background", "no-background"])
def test_render_refuses_channels_last_texture_maps_naming_them(images, background):
    torch.manual_seed(0)
    model = Unicorn(tiny_config(**({} if background else {"background": None}))).eval()
    with torch.no_grad():
        pred = model.predict(images)
    bkg = pred.background
    # (B, Ht, Wt, 3) maps read as Ht-channel maps would fail in the renderer, naming its background
    with pytest.raises(ShapeError, match=r"^maps must have shape \(B, 3, Ht, Wt\), got \(3, 16, 16, 3\)$"):
        model.render(pred.verts, pred.texture.permute(0, 2, 3, 1), pred.R, pred.T, bkg)
    with pytest.raises(TypeError, match=r"^maps must be a floating point tensor, got torch.uint8$"):
        model.render(pred.verts, (pred.texture * 255).to(torch.uint8), pred.R, pred.T, bkg)
    # the same maps in channels-last memory are the (B, 3, Ht, Wt) maps they hold
    rgb, _ = model.render(pred.verts, pred.texture, pred.R, pred.T, bkg)
    maps = pred.texture.contiguous(memory_format=torch.channels_last)
    assert torch.equal(model.render(pred.verts, maps, pred.R, pred.T, bkg)[0], rgb)


def test_one_image_in_training_mode_is_refused_where_batchnorm_cannot_normalise_it(tiny_model, images):
    # at 32 px the last ResNet stage is 1 x 1: one image leaves BatchNorm a single value per channel
    with pytest.raises(
        ValueError, match=r"^one 32 x 32 image in training mode: .*\(layer4's map is 1 x 1\); call model"
    ):
        tiny_model.predict(images[:1])
    tiny_model.predict(images[:2])  # two images: batch statistics
    tiny_model.eval()
    with torch.no_grad():  # running statistics: the image's prediction alone is its prediction in a batch
        one, batch = tiny_model.predict(images[:1]), tiny_model.predict(images)
    assert torch.allclose(one.verts, batch.verts[:1], atol=1e-6) and torch.allclose(one.R, batch.R[:1], atol=1e-6)
    assert torch.allclose(one.texture, batch.texture[:1], atol=1e-6)


def test_zero_init_gives_ellipsoid_identity_scale_anchor_poses(tiny_model, images):
    tiny_model.set_active_dims(shape=32, texture=128, background=128)
    pred = tiny_model.predict(images)
    template = tiny_model.template.verts
    assert torch.equal(pred.canonical_verts, template.expand_as(pred.canonical_verts))
    assert torch.equal(pred.scale, torch.ones_like(pred.scale))
    assert torch.equal(pred.verts, pred.canonical_verts)
    assert pred.shape_code.abs().sum() == 0 and pred.texture_code.abs().sum() == 0
    assert torch.allclose(pred.texture, torch.full_like(pred.texture, 0.5))  # zero code: grey
    init = tiny_model.pose.R_init
    anchors = azim_elev_roll_to_rotation(init[:, 0], init[:, 1], init[:, 2])
    assert torch.allclose(pred.poses.R, anchors[:, None].expand_as(pred.poses.R), atol=1e-6)
    assert torch.allclose(pred.T, torch.tensor([0.0, 0.0, 2.732]).expand_as(pred.T))
    assert torch.allclose(pred.R, anchors[pred.poses.best], atol=1e-6)


@pytest.mark.parametrize(("branch", "active"), [("shape", 2), ("texture", 8), ("background", 4)])
def test_masked_code_dims_change_nothing(tiny_model, images, branch, active):
    randomize_heads(tiny_model, std=0.1)
    tiny_model.set_active_dims(**{branch: active})
    head = getattr(tiny_model, branch)
    with torch.no_grad():
        before = tiny_model.predict(images)
        head.regressor[-1].weight[active:] += 1.0  # perturb only the masked code dims
        head.regressor[-1].bias[active:] -= 2.0
        after = tiny_model.predict(images)
        for name in ("verts", "texture", "background"):
            assert torch.equal(getattr(before, name), getattr(after, name)), name
        head.regressor[-1].bias[:active] += 0.5  # the active dims do matter
        changed = tiny_model.predict(images)
    key = {"shape": "verts", "texture": "texture", "background": "background"}[branch]
    assert not torch.allclose(getattr(before, key), getattr(changed, key))
    state = tiny_model.state_dict()
    assert int(state[f"{branch}.mask.active"]) == active


def test_stage_switches_and_texture_averaging(tiny_model, images):
    randomize_heads(tiny_model, std=0.1)
    tiny_model.set_active_dims(shape=4)
    tiny_model.set_stage_switches(translation=False, deformation=False, scale=False)
    pred = tiny_model.predict(images)
    assert torch.allclose(pred.T, torch.tensor([0.0, 0.0, 2.732]).expand_as(pred.T))
    assert torch.equal(pred.verts, tiny_model.template.verts.expand_as(pred.verts))
    assert torch.equal(pred.scale, torch.ones_like(pred.scale))
    tiny_model.set_stage_switches(translation=True, deformation=True, scale=True)
    pred = tiny_model.predict(images, average_texture=True)
    assert not torch.equal(pred.verts, tiny_model.template.verts.expand_as(pred.verts))
    flat = pred.texture.flatten(2)
    assert torch.allclose(flat, flat[..., :1].expand_as(flat))
    assert torch.allclose(flat[..., 0], tiny_model.predict(images).texture.mean((2, 3)), atol=1e-6)


@pytest.mark.parametrize("average", [False, True])
def test_texture_averaging_as_a_tensor_gives_the_python_choice(tiny_model, images, average):
    # a compiled step passes the choice as a 0-dim bool tensor (one graph for both): the same maps and gradients
    randomize_heads(tiny_model, std=0.1)
    feats = tiny_model.encode(images, tiny_model.branches())
    results = []
    for choice in (average, torch.tensor(average)):
        tiny_model.zero_grad(set_to_none=True)
        texture = tiny_model.predict_3d(feats, choice).texture
        (texture * torch.linspace(0, 1, texture.numel()).view_as(texture)).sum().backward(retain_graph=True)
        grads = [p.grad.clone() for p in tiny_model.texture.parameters() if p.grad is not None]
        results.append((texture.detach(), grads))
    (maps, grads), (maps_t, grads_t) = results
    assert torch.equal(maps_t, maps) and len(grads_t) == len(grads) > 0
    assert all(torch.equal(a, b) for a, b in zip(grads_t, grads))


def test_encoder_width_sets_the_features_every_head_reads():
    torch.manual_seed(0)
    model = Unicorn(tiny_config("real", "big", encoder={"shared": False, "width": 16}))
    assert [e.out_features for e in model.encoders] == [128] * 4
    x = ellipsoid_images(2)
    assert tuple(model.encode(x, model.branches())["shape"].shape) == (2, 128)
    objectives = Objectives.from_config(model.config["loss"], model)
    pose, step = objectives.pose_step(model, x), objectives.step_3d(model, x)
    assert all(torch.isfinite(v) for v in [*pose.values(), *step.values()])
    with pytest.raises(ValueError, match="width"):
        merge_config(encoder={"width": 0})


def test_pooled_stages_set_the_features_every_head_reads():
    torch.manual_seed(0)
    model = Unicorn(tiny_config(encoder={"pooled": ["layer3", "layer4"], "width": 16, "own": ["texture"]}))
    assert [e.out_features for e in model.encoders] == [64 + 128] * 2  # layer3: 4 x width, layer4: 8 x width
    x = ellipsoid_images(2)
    assert tuple(model.encode(x, model.branches())["texture"].shape) == (2, 192)
    objectives = Objectives.from_config(model.config["loss"], model)
    pose, step = objectives.pose_step(model, x), objectives.step_3d(model, x)
    assert all(torch.isfinite(v) for v in [*pose.values(), *step.values()])
    for pooled in ([], ["layer0"], ["layer4", "layer4"]):
        with pytest.raises(ValueError, match=r"encoder.pooled must name distinct stages"):
            merge_config(encoder={"pooled": pooled})


def test_own_encoders_beside_the_shared_one():
    torch.manual_seed(0)
    model = Unicorn(tiny_config(encoder={"own": ["background", "texture"], "width": 16}))
    assert model.encoder_index == {"shape": 0, "texture": 1, "pose": 0, "background": 2}
    assert len(model.encoders) == 3 and model.encoder_mates("pose") == ("shape",)
    assert model.encoder_mates("texture") == ()
    x = ellipsoid_images(2)
    feats = model.encode(x, model.branches())
    assert feats["shape"] is feats["pose"]
    for branch, i in model.encoder_index.items():
        assert torch.equal(feats[branch], model.encoders[i](x))
    assert not torch.allclose(feats["texture"], feats["background"])
    bad = {
        "needs encoder.shared=true": {"shared": False, "own": ["pose"]},
        "'wheels' is not a branch": {"own": ["wheels"]},
        "names a branch twice": {"own": ["pose", "pose"]},
        "set encoder.shared=false": {"own": ["shape", "texture", "pose", "background"]},
    }
    for message, encoder in bad.items():
        with pytest.raises(ValueError, match=message):
            merge_config(encoder=encoder)
    with pytest.raises(ValueError, match="'background' is not a branch"):
        merge_config(encoder={"own": ["background"]}, background=None)


def test_shapenet_model_without_background():
    torch.manual_seed(0)
    model = Unicorn(tiny_config("shapenet", "big"))
    assert model.background is None and len(model.encoders) == 3
    assert model.shape.field.linear_x.out_features == 512
    assert model.config["renderer"]["focal_length"] > 3.7
    x = ellipsoid_images(2)
    objectives = Objectives.from_config(model.config["loss"], model)
    pose, step = objectives.pose_step(model, x), objectives.step_3d(model, x)
    assert all(torch.isfinite(v) for v in [*pose.values(), *step.values()])


@pytest.mark.parametrize(("shape", "texture"), [(True, True), (True, False), (False, True)])
def test_symmetric_shape_and_texture_render_mirrored_views_as_mirrored_images(shape, texture):
    # a scene symmetric through z = 0 seen with R' = M R F (M mirrors z, F flips the view's x) is the view of its
    # mirror image flipped left-right: the mirrored camera's picture is the first picture flipped
    torch.manual_seed(0)
    model = Unicorn(tiny_config(shape={"symmetric": shape, "active_dims": 4}, texture={"symmetric": texture})).eval()
    randomize_heads(model, std=0.3)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():  # texture maps far from one colour, so that an asymmetric one shows
        for module in model.texture.generator.modules():
            if isinstance(module, torch.nn.Conv2d):
                module.weight.copy_(torch.randn(module.weight.shape, generator=g) * 0.5)
    mirror, flip = torch.diag(torch.tensor([1.0, 1.0, -1.0])), torch.diag(torch.tensor([-1.0, 1.0, 1.0]))
    R = azim_elev_roll_to_rotation(torch.tensor([40.0]), torch.tensor([20.0]), torch.tensor([10.0]))
    T = torch.tensor([[0.1, -0.05, 2.732]])
    with torch.no_grad():
        pred = model.predict(ellipsoid_images(1))
        rgb, alpha = model.render(pred.verts, pred.texture, R, T)
        rgb_m, alpha_m = model.render(pred.verts, pred.texture, mirror @ R @ flip, T @ flip)
    assert alpha.sum() > 50 and pred.texture.std() > 0.2  # the object covers part of the image, in many colours
    assert (torch.allclose(alpha_m, alpha.flip(-1), atol=1e-4)) == shape
    assert (torch.allclose(rgb_m, rgb.flip(-1), atol=1e-4)) == (shape and texture)


def test_symmetric_texture_needs_the_seamless_uvs_and_an_even_size():
    with pytest.raises(ValueError, match="texture.symmetric needs template.uv_mode='seamless'"):
        merge_config(texture={"symmetric": True}, template={"uv_mode": "reference"})
    with pytest.raises(ValueError, match="texture.symmetric needs an even texture.size"):
        merge_config(texture={"symmetric": True, "size": 15})


def test_the_config_follows_the_background_colour_of_loaded_weights(tmp_path):
    """The colour is a buffer of the renderer: a state dict brings its own, and the config, which save_model writes
    beside the weights, says the colour the model renders."""
    from unicorn.io import load_model, save_model

    source = Unicorn(tiny_config(renderer={"background_color": (0.1, 0.5, 0.75)}))
    model = Unicorn(tiny_config())
    model.load_state_dict(source.state_dict())
    assert model.config["renderer"]["background_color"] == (0.1, 0.5, 0.75)  # the decimals given, not float32's
    far = torch.tensor([[0.0, 0.0, 100.0]])  # every pixel is background
    verts, maps = far.expand(1, 642, 3), torch.ones(1, 3, 16, 16)
    with torch.no_grad():
        rgb, _ = model.render(verts, maps, torch.eye(3)[None], torch.zeros(1, 3))
    assert torch.allclose(rgb[0, :, 0, 0], torch.tensor([0.1, 0.5, 0.75]))
    path = save_model(model, tmp_path / "model.pt")
    saved = torch.load(path, weights_only=True)
    assert saved["config"]["renderer"]["background_color"] == (0.1, 0.5, 0.75)
    loaded, _ = load_model(path)
    assert loaded.config["renderer"] == model.config["renderer"]
    # a state dict of the colour already configured leaves the config as written
    model.load_state_dict(source.state_dict())
    assert model.config["renderer"]["background_color"] == (0.1, 0.5, 0.75)
