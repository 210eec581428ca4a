"""Released-checkpoint loading, tested on state dicts written in the reference's names and shapes."""

from __future__ import annotations

import re

import pytest
import torch

from tests.support.checkpoints import reference_state
from tests.support.evaluation import tiny_model
from unicorn.errors import UserError
from unicorn.io import (
    CheckpointError,
    ReferenceCheckpointError,
    config_from_reference,
    convert_reference_state_dict,
    load_model,
    load_reference_checkpoint,
    save_model,
)


def real_kwargs() -> dict:
    return {
        "img_size": 32,
        "mesh": {"init": "ellipse", "scale": 0.6, "deform_fields": {"powers": [2, 8, 32], "milestones": [10, 20, 30]},
                 "texture_uv": {"powers": [2, 8, 32, 128], "milestones": [0, 10, 20, 30]}},
        "background": {"powers": [4, 8, 32, 128], "milestones": [0, 10, 20, 30]},
        "renderer": {"cameras": {"name": "fov", "fov": 30}, "faces_per_pixel": 25},
        "rend_predictor": {"n_elev_azim": [1, 6], "azim_range": [0, 360], "elev_range": [-10, 30],
                           "roll_range": [-30, 30], "T_range": [0.3, 0.3, 0.3], "scale_range": [0.3, 0.3, 0.3]},
        "milestones": {"freeze_T_predictor": 2, "freeze_shape": 4, "freeze_scale_predictor": 60},
    }  # fmt: skip


def test_small_checkpoint_maps_every_tensor():
    state = reference_state()
    model = load_reference_checkpoint(state)
    assert len(model.encoders) == 1 and not model.training
    enc = model.encoders[0]
    assert torch.equal(enc.conv1.weight, state["encoder.encoder.0.weight"])
    assert torch.equal(enc.bn1.running_var, state["encoder.encoder.1.running_var"])
    assert torch.equal(enc.layer4[1].bn2.weight, state["encoder.encoder.7.1.bn2.weight"])
    assert torch.equal(enc.layer2[0].downsample[0].weight, state["encoder.encoder.5.0.downsample.0.weight"])
    assert torch.equal(model.shape.field.mlp[4].weight, state["deform_field.field.mlp.4.weight"])
    assert torch.equal(model.texture.generator.conv_rgb[3].weight, state["txt_generator.generator.conv_rgb.3.weight"])
    assert torch.equal(model.background.regressor[6].bias, state["bkg_generator.regressor.6.bias"])
    assert torch.equal(model.pose.T_regressors[5][2].weight, state["T_regressors.5.2.weight"])
    assert torch.equal(model.scale.regressor[0].weight, state["scale_regressor.0.weight"])
    assert torch.equal(model.pose.proba_regressor[6].bias, state["proba_regressor.6.bias"])
    # the reference's [1, 0, 2] channel swap lands in the last rotation layer
    assert torch.equal(model.pose.rot_regressors[2][6].weight, state["rot_regressors.2.6.weight"][[1, 0, 2]])
    assert torch.equal(model.pose.rot_regressors[2][4].weight, state["rot_regressors.2.4.weight"])
    cfg = model.config
    assert cfg["template"]["uv_mode"] == "reference" and cfg["renderer"]["composite"] == "reference"
    assert cfg["template"]["bottom"] == 1.0  # the reference's whole ellipsoid, whatever the presets' template
    assert model.active_dims() == {"shape": 32, "texture": 128, "background": 128}  # no epoch: final stage
    assert cfg["image_size"] == 32 and cfg["texture"]["size"] == 16


def test_rotation_swap_gives_the_reference_angles():
    state = reference_state()
    for k in range(6):
        state[f"rot_regressors.{k}.6.weight"].zero_()
        state[f"rot_regressors.{k}.6.bias"] = torch.tensor([0.1, 0.5, -0.3])  # reference channels
    model = load_reference_checkpoint(state)
    with torch.no_grad():
        pred = model.predict(torch.rand(2, 3, 32, 32))
    # reference: (azim, elev, roll) = tanh(out)[[1, 0, 2]] * range + init
    offsets = torch.tanh(torch.tensor([0.5, 0.1, -0.3])) * torch.tensor([31.2, 20.8, 31.2])
    expected = model.pose.R_init + offsets
    assert torch.allclose(pred.poses.angles, expected[:, None].expand(6, 2, 3), atol=1e-4)
    rec, _ = model(torch.rand(2, 3, 32, 32))
    assert rec.shape == (2, 3, 32, 32) and torch.isfinite(rec).all()


def test_reference_compositing_formula():
    model = load_reference_checkpoint(reference_state())
    with torch.no_grad():
        pred = model.predict(torch.rand(2, 3, 32, 32))
        rec, alpha = model.render(pred.verts, pred.texture, pred.R, pred.T, pred.background)
        white = model.renderer(pred.verts, model.template.faces, model.textures(pred.texture), R=pred.R, T=pred.T)
    a = white[:, 3:]
    assert torch.allclose(alpha, a)
    assert torch.allclose(rec, white[:, :3] * a + (1 - a) * pred.background, atol=1e-6)
    assert 0.05 < float(a.mean()) < 0.95


def test_big_checkpoint_with_kwargs_epoch_and_file(tmp_path):
    checkpoint = {"epoch": 15, "model_name": "unicorn", "model_kwargs": real_kwargs(),
                  "model_state": reference_state(big=True), "optimizer_state": {}}  # fmt: skip
    path = tmp_path / "model.pkl"
    torch.save(checkpoint, path)
    model = load_reference_checkpoint(path, with_perceptual=True)
    assert len(model.encoders) == 4
    assert torch.equal(model.encoders[2].conv1.weight, checkpoint["model_state"]["encoder_pose.encoder.0.weight"])
    assert model.active_dims() == {"shape": 2, "texture": 8, "background": 8}  # epoch 15: second stage
    assert bool(model.pose.use_translation) and bool(model.shape.use_deformation)
    assert not bool(model.scale.use_scale)  # freeze_scale_predictor 60 still live at epoch 15
    cfg = model.config
    assert cfg["texture"]["code_dim"] == 512 and cfg["texture"]["min_features"] == 64 and cfg["shape"]["code_dim"] == 64
    vgg = model.perceptual.vgg.features
    assert torch.equal(vgg[14].weight, checkpoint["model_state"]["perceptual_loss.slice3.14.weight"])
    x = torch.rand(2, 3, 32, 32)
    assert model.perceptual(x, x).abs().max() < 1e-8


def test_shapenet_checkpoint_and_key_checks():
    state = reference_state(background=False, field_units=512)
    cfg = config_from_reference(state)
    assert cfg["background"] is None and cfg["shape"]["n_field_units"] == 512 and cfg["template"]["scale"] == 0.4
    assert cfg["pose"]["elev_range"] == (30.0, 30.0) and cfg["renderer"]["focal_length"] > 3.7
    model = load_reference_checkpoint(state, image_size=32)
    assert model.background is None
    bad = dict(state, **{"mystery.weight": torch.zeros(1)})
    with pytest.raises(KeyError, match="mystery"):
        convert_reference_state_dict(bad)
    ours, vgg = convert_reference_state_dict(bad, strict=False)
    assert "mystery.weight" not in ours and len(vgg) == 14
    missing = dict(state)
    del missing["scale_regressor.0.weight"]
    with pytest.raises(KeyError, match="scale.regressor.0.weight"):
        load_reference_checkpoint(missing, image_size=32)
    # a tensor the model's sizes are read from
    del missing["txt_generator.regressor.0.weight"]
    with pytest.raises(ReferenceCheckpointError, match=r"^missing key 'txt_generator\.regressor\.0\.weight'"):
        load_reference_checkpoint(missing, image_size=32)
    with pytest.raises(ReferenceCheckpointError, match="^the checkpoint holds no perceptual_loss weights"):
        without_vgg = {k: v for k, v in state.items() if not k.startswith("perceptual_loss.")}
        load_reference_checkpoint(without_vgg, image_size=32, with_perceptual=True)
    assert issubclass(ReferenceCheckpointError, UserError) and issubclass(ReferenceCheckpointError, KeyError)


def test_a_missing_layer_tensor_is_named_not_read_as_a_shorter_network():
    state = reference_state()
    del state["deform_field.field.mlp.4.weight"]  # its bias stays: the layer count cannot come from the weights
    with pytest.raises(ReferenceCheckpointError, match=r"^missing key 'deform_field\.field\.mlp\.4\.weight'"):
        load_reference_checkpoint(state)


@pytest.mark.parametrize(
    "section, value, message",
    [
        (("mesh", "init"), "bogus", r"model_kwargs\['mesh'\]\['init'\] = 'bogus' is not a template"),
        (("mesh", "init"), 3, r"model_kwargs\['mesh'\]\['init'\] = 3 is not a template"),
        (("renderer", "cameras"), {"name": "orthographic"}, r"\['name'\] = 'orthographic' is not a camera"),
        (("renderer", "cameras"), {"name": "perspective"}, r"perspective camera without focal_length"),
        (("background", "milestones"), "0,10,20,30", r"\['milestones'\] = '0,10,20,30' is not a list of numbers"),
        (("mesh", "texture_uv"), {"powers": [2, 8, 32, 128], "milestones": [0, None, 20, 30]}, r"None is not a"),
        (("renderer", "faces_per_pixel"), 1e9, r"\['faces_per_pixel'\] = 1000000000.0 is not a whole number > 0"),
        (("renderer", "sigma"), "1e-4", r"model_kwargs\['renderer'\]\['sigma'\] = '1e-4' is not a finite number"),
    ],
)
def test_a_released_files_settings_of_the_wrong_kind_are_named(section, value, message):
    kwargs = real_kwargs()
    kwargs[section[0]][section[1]] = value
    checkpoint = {"epoch": 15, "model_kwargs": kwargs, "model_state": reference_state()}
    with pytest.raises(UserError, match=message):
        load_reference_checkpoint(checkpoint)


def test_a_negative_epoch_is_named():
    checkpoint = {"epoch": -3, "model_kwargs": real_kwargs(), "model_state": reference_state()}
    with pytest.raises(UserError, match=r"^epoch = -3 is not a whole number >= 0$"):
        load_reference_checkpoint(checkpoint)


def test_the_reference_templates_are_read_from_their_names():
    for init, axes, level in [
        ("ellipse", (1.0, 0.7, 0.7), 3),
        ("sphere", (1.0, 1.0, 1.0), 3),
        ("hr_ellipse", (1.0, 0.7, 0.7), 4),
    ]:
        kwargs = dict(real_kwargs(), mesh={**real_kwargs()["mesh"], "init": init})
        cfg = config_from_reference({"epoch": 15, "model_kwargs": kwargs, "model_state": reference_state()})
        assert (tuple(cfg["template"]["axes"]), cfg["template"]["level"]) == (axes, level), init


def test_a_file_of_another_format_or_that_does_not_convert_is_named(tmp_path):
    """Given a path, every error names the file; a checkpoint of the other formats is sent to load_model."""
    plain = save_model(tiny_model("real"), tmp_path / "model.pt")
    lightning = tmp_path / "last.ckpt"
    torch.save({"state_dict": {"model.w": torch.zeros(1)}, "hyper_parameters": {"model": {}}}, lightning)
    for path, kind in [(plain, "a unicorn.io.save_model file"), (lightning, "a unicorn-train checkpoint")]:
        expected = rf"^{re.escape(str(path))} is {kind}, not a released UNICORN checkpoint: load it"
        with pytest.raises(CheckpointError, match=expected):
            load_reference_checkpoint(path)
    torch.save([1, 2], tmp_path / "list.pkl")
    with pytest.raises(CheckpointError, match=r"list.pkl holds a list, not a released UNICORN checkpoint"):
        load_reference_checkpoint(tmp_path / "list.pkl")

    state = reference_state()
    del state["scale_regressor.0.weight"]
    cases = [
        ({"epoch": -3, "model_state": reference_state()}, CheckpointError, r"epoch = -3 is not a whole number"),
        ({"epoch": 3, "model_state": state}, ReferenceCheckpointError, r"checkpoint does not fit the model: missing"),
        (
            {"model_state": reference_state(), "model_kwargs": {"rend_predictor": {"n_elev_azim": [2, 5]}}},
            CheckpointError,
            r"checkpoint has 6 pose candidates but n_elev_azim = \[2, 5\]",
        ),
    ]
    for i, (checkpoint, error, message) in enumerate(cases):
        path = tmp_path / f"released{i}.pkl"
        torch.save(checkpoint, path)
        with pytest.raises(error, match=rf"^released checkpoint {re.escape(str(path))}: {message}") as info:
            load_reference_checkpoint(path)
        assert isinstance(info.value, UserError)


def _released_file(tmp_path) -> tuple:
    state = reference_state()
    path = tmp_path / "model.pkl"
    torch.save({"epoch": 5, "model_kwargs": {}, "model_state": state}, path)
    return path, state


def test_the_meta_device_is_refused_before_reading(tmp_path):
    """load_model's rule: meta tensors hold no values to load into the model."""
    path, _ = _released_file(tmp_path)
    for checkpoint in (path, tmp_path / "absent.pkl", {"model_state": reference_state()}):
        with pytest.raises(ValueError, match=r"^map_location='meta' loads no values"):
            load_reference_checkpoint(checkpoint, map_location="meta")


def test_a_remapping_map_location_loads_on_the_cpu(tmp_path):
    path, state = _released_file(tmp_path)
    for map_location in ({"cuda:0": "cpu"}, lambda storage, location: storage):
        model = load_reference_checkpoint(path, map_location=map_location)
        assert {t.device.type for t in (*model.parameters(), *model.buffers())} == {"cpu"}
        assert torch.equal(model.encoders[0].conv1.weight, state["encoder.encoder.0.weight"])


@pytest.mark.gpu
@pytest.mark.parametrize("given", ["path", "dict"])
def test_the_model_is_returned_on_map_location(tmp_path, given):
    path, _ = _released_file(tmp_path)
    checkpoint = path if given == "path" else torch.load(path)
    model = load_reference_checkpoint(checkpoint, map_location="cuda", with_perceptual=True)
    assert {t.device.type for t in (*model.parameters(), *model.buffers())} == {"cuda"} and not model.training
    cpu = load_reference_checkpoint(path)
    images = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        expected, actual = cpu.predict(images), model.predict(images.cuda())
    torch.testing.assert_close(actual.verts.cpu(), expected.verts, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(actual.texture.cpu(), expected.texture, rtol=1e-4, atol=1e-5)


def _older_reference_file(state: dict) -> dict:
    """``state`` as the older reference versions the small released models come from saved it (their ``Unicorn``
    state dict as read in the reference repository): the camera buffers ``T_cam`` (the prior translation) and
    ``R_cam`` beside ``T_init = 0``, the whole VGG16 of the perceptual loss (slices 1 to 5) with its normalisation
    buffers, the blur kernels of shape (1, 3, 3)."""
    state = dict(state)
    state.update({"T_init": torch.zeros(3), "T_cam": torch.tensor([0.0, 0.0, 2.732]), "R_cam": torch.eye(3)})
    state.update({"perceptual_loss.mean_rgb": torch.rand(3), "perceptual_loss.std_rgb": torch.rand(3)})
    for name, i, cin in (("slice4", 17, 256), ("slice4", 19, 512), ("slice4", 21, 512), ("slice5", 24, 512),
                         ("slice5", 26, 512), ("slice5", 28, 512)):  # fmt: skip
        state[f"perceptual_loss.{name}.{i}.weight"] = torch.zeros(512, cin, 3, 3)
        state[f"perceptual_loss.{name}.{i}.bias"] = torch.zeros(512)
    for key in [k for k in state if k.endswith(".kernel")]:
        state[key] = torch.rand(1, 3, 3)
    return state


def test_a_file_of_the_older_reference_versions_loads_with_the_prior_translation(tmp_path):
    state = _older_reference_file(reference_state())
    for k in range(6):  # no translation offset: the object at the prior translation
        state[f"T_regressors.{k}.6.weight"].zero_()
        state[f"T_regressors.{k}.6.bias"].zero_()
    path = tmp_path / "model.pkl"
    torch.save({"epoch": 700, "model_kwargs": real_kwargs(), "model_state": state}, path)
    model = load_reference_checkpoint(path, with_perceptual=True)
    assert torch.equal(model.perceptual.vgg.features[0].weight, state["perceptual_loss.slice1.0.weight"])
    assert load_model(path)[1].format == "reference"  # unicorn-eval's and unicorn-reconstruct's reader
    with torch.no_grad():
        T = model.predict(torch.rand(2, 3, 32, 32)).T
    # T_cam's translation, not T_init = 0
    torch.testing.assert_close(T, torch.tensor([0.0, 0.0, 2.732]).expand(2, 3))


def test_a_model_saved_from_multi_gpu_training_loads():
    """The reference saves ``DistributedDataParallel``'s state dict, every name under ``module.``."""
    state = reference_state()
    model = load_reference_checkpoint({"epoch": 3, "model_state": {f"module.{k}": v for k, v in state.items()}})
    assert torch.equal(model.encoders[0].conv1.weight, state["encoder.encoder.0.weight"])
    assert torch.equal(model.pose.rot_regressors[1][6].weight, state["rot_regressors.1.6.weight"][[1, 0, 2]])


def test_a_state_dict_key_that_is_not_a_name_is_named_in_one_line(tmp_path):
    path = tmp_path / "model.pkl"
    torch.save({"epoch": 3, "model_state": {**reference_state(), 7: torch.zeros(2)}}, path)
    with pytest.raises(CheckpointError, match=r"model_state has the key 7 \(an int\), not a parameter name$"):
        load_reference_checkpoint(path)


def test_a_file_with_nan_weights_is_refused_as_load_model_refuses_it(tmp_path):
    state = reference_state()
    state["deform_field.field.mlp.2.weight"][0, 0] = float("nan")
    path = tmp_path / "model.pkl"
    torch.save({"epoch": 5, "model_state": state}, path)
    expected = rf"^checkpoint {re.escape(str(path))}: its weight shape\.field\.mlp\.2\.weight holds NaN or infinite"
    for load in (load_reference_checkpoint, load_model):
        with pytest.raises(CheckpointError, match=expected):
            load(path)


def test_another_programs_checkpoint_is_named_by_its_keys_not_read_as_a_state_dict(tmp_path):
    """A Lightning checkpoint without hyper-parameters (another program's) has no model_state and is no state dict."""
    path = tmp_path / "last.pkl"
    torch.save({"epoch": 3, "global_step": 10, "state_dict": {"net.w": torch.zeros(2)}}, path)
    expected = (
        rf"^released checkpoint {re.escape(str(path))}: no 'model_state' and not a state dict "
        r"\(keys \['epoch', 'global_step', 'state_dict'\]\): not a released UNICORN checkpoint$"
    )
    with pytest.raises(CheckpointError, match=expected):
        load_reference_checkpoint(path)
