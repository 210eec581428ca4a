"""load_model: the three checkpoint formats, their metadata, overrides and errors."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.support.checkpoints import reference_state
from tests.support.evaluation import IMAGE_SIZE, tiny_model
from unicorn.io import CheckpointError, load_model, load_reference_checkpoint, read_checkpoint, save_model
from unicorn.io.checkpoints import MapLocationError, init_weights
from unicorn.io.serialization import INTEGRITY_KEY


def _same_prediction(a, b) -> None:
    """The same weights, tensor for tensor (an untrained model's prediction hardly depends on them), and so the same
    prediction."""
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    assert all(torch.equal(sa[k], sb[k]) for k in sa), [k for k in sa if not torch.equal(sa[k], sb[k])]
    x = torch.rand(2, 3, IMAGE_SIZE, IMAGE_SIZE, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        pa, pb = a.predict(x), b.predict(x)
    for name in ("verts", "texture", "R", "T"):
        torch.testing.assert_close(getattr(pa, name), getattr(pb, name))


def test_plain_round_trip(tmp_path: Path) -> None:
    model = tiny_model("real", seed=1)
    path = save_model(model, tmp_path / "m.pt", epoch=3, step=40, average_texture=True, dataset={"name": "folder"})
    loaded, info = load_model(path)
    assert info.format == "plain" and info.epoch == 3 and info.step == 40 and info.average_texture
    assert info.dataset == {"name": "folder"} and not loaded.training
    _same_prediction(model, loaded)


def test_save_model_replaces_a_file_only_when_asked(tmp_path: Path) -> None:
    mine = tmp_path / "car.pkl"
    mine.write_bytes(b"the user's file")
    with pytest.raises(FileExistsError, match=rf"^{re.escape(str(mine))} exists: pass overwrite=True to replace it"):
        save_model(tiny_model("real", seed=1), mine)
    assert mine.read_bytes() == b"the user's file"
    loaded, _ = load_model(save_model(tiny_model("real", seed=1), mine, overwrite=True, step=2))
    _same_prediction(tiny_model("real", seed=1), loaded)


def test_checkpoint_from_before_the_encoder_width_loads_resnet18(tmp_path: Path) -> None:
    model = tiny_model("real", seed=1)
    del model.config["encoder"]["width"]  # what versions before the setting stored
    loaded, _ = load_model(save_model(model, tmp_path / "m.pt"))
    assert loaded.config["encoder"]["width"] == 64 and loaded.encoders[0].out_features == 512
    _same_prediction(model, loaded)


def _lightning_checkpoint(path: Path, average: float = 0.0) -> torch.nn.Module:
    """A checkpoint written by Lightning itself for the training module (no training needed)."""
    import lightning as L

    from unicorn.lit.module import UnicornLitModule

    module = UnicornLitModule(tiny_model("real", seed=2).config)
    module.texture_average_p.fill_(average)
    trainer = L.Trainer(
        logger=False, enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
        max_steps=0, accelerator="cpu",
    )  # fmt: skip
    trainer.strategy.connect(module)
    module.trainer = trainer
    trainer.save_checkpoint(path)
    return module.model


def test_lightning_checkpoint_of_a_run(tmp_path: Path) -> None:
    run = tmp_path / "run"
    (run / "checkpoints").mkdir(parents=True)
    (run / "config.yaml").write_text("dataset:\n  name: synthetic\n  root: /data/synth\n  categories: [chair]\n")
    model = _lightning_checkpoint(run / "checkpoints" / "last.ckpt", average=1.0)
    loaded, info = load_model(run / "checkpoints" / "last.ckpt")
    assert info.format == "lightning" and info.step == 0 and info.extra["stage"] == 1
    assert info.average_texture  # the mean-texture phase is read from the module's buffer
    assert info.run_dir == run and info.dataset == {"name": "synthetic", "root": "/data/synth", "categories": ["chair"]}
    assert loaded.config["loss"]["perceptual"] is None  # no VGG weights needed to evaluate
    _same_prediction(model.eval(), loaded)


def test_reference_checkpoint_and_template_override(tmp_path: Path) -> None:
    state = reference_state()
    torch.save({"epoch": 5, "model_kwargs": {}, "model_state": state}, tmp_path / "model.pkl")
    model, info = load_model(tmp_path / "model.pkl")
    assert info.format == "reference" and info.epoch == 5 and info.run_dir is None
    assert torch.equal(model.encoders[0].conv1.weight, state["encoder.encoder.0.weight"])  # the file's weights
    assert model.config["template"]["uv_mode"] == "reference" and model.template.verts.shape[0] == 642
    fine, _ = load_model(tmp_path / "model.pkl", overrides={"template": {"level": 4}})
    assert fine.template.verts.shape[0] == 2562  # the template is not part of the weights


def test_errors(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        load_model(tmp_path / "missing.ckpt")
    (tmp_path / "junk.ckpt").write_bytes(b"definitely not a torch file")
    with pytest.raises(CheckpointError, match="cannot read checkpoint"):
        load_model(tmp_path / "junk.ckpt")
    torch.save({"weights": torch.zeros(1)}, tmp_path / "other.pt")
    with pytest.raises(CheckpointError, match="not a UNICORN checkpoint"):
        load_model(tmp_path / "other.pt")
    path = save_model(tiny_model("real"), tmp_path / "m.pt")
    data = torch.load(path, weights_only=True)
    data.pop(INTEGRITY_KEY)  # an unsealed file (edited by hand): its weights are checked against the model
    data["state_dict"].pop("scale.regressor.0.weight")
    torch.save(data, tmp_path / "broken.pt")
    with pytest.raises(CheckpointError, match="does not fit"):
        load_model(tmp_path / "broken.pt")


@pytest.mark.parametrize("value", [float("nan"), float("inf")], ids=["nan", "inf"])
def test_weights_no_prediction_can_come_from_are_refused_by_name(tmp_path: Path, value: float) -> None:
    model = tiny_model("real")
    name = "encoders.0.layer1.0.conv1.weight"
    model.state_dict()[name].view(-1)[3] = value
    path = save_model(model, tmp_path / "m.pt")
    with pytest.raises(CheckpointError, match=rf"m\.pt: its weight {re.escape(name)} holds NaN or infinite values$"):
        load_model(path)
    with pytest.raises(CheckpointError, match="holds NaN or infinite values"):
        init_weights(tiny_model("real"), path)  # init_from loads through load_model


def test_a_released_checkpoint_with_a_negative_running_variance_is_refused(tmp_path: Path) -> None:
    state = reference_state()
    name = next(k for k in state if k.endswith("running_var"))
    state[name] = state[name].clone()
    state[name][0] = -1.0
    torch.save({"epoch": 5, "model_kwargs": {}, "model_state": state}, tmp_path / "model.pkl")
    with pytest.raises(CheckpointError, match=r"model\.pkl: its batch-norm running variance \S+ holds negative values"):
        load_model(tmp_path / "model.pkl")


def test_the_meta_device_is_refused_before_reading(tmp_path: Path) -> None:
    path = save_model(tiny_model("real"), tmp_path / "m.pt")
    with pytest.raises(ValueError, match=r"map_location='meta' loads no values"):
        load_model(path, map_location="meta")


@pytest.mark.parametrize("device", ["cpux", "", "cuda:99", torch.device("cuda", 99), "cuda:257"], ids=repr)
def test_a_device_this_machine_lacks_is_blamed_not_the_file(tmp_path: Path, device) -> None:
    path = save_model(tiny_model("real"), tmp_path / "m.pt")
    released = tmp_path / "model.pkl"
    torch.save({"epoch": 5, "model_kwargs": {}, "model_state": reference_state()}, released)
    for load, file in ((load_model, path), (read_checkpoint, path), (load_reference_checkpoint, released)):
        with pytest.raises(MapLocationError) as info:
            load(file, map_location=device)
        message = str(info.value)
        assert message.startswith(f"map_location={device!r}") and "\n" not in message, message
        assert not isinstance(info.value, CheckpointError) and str(file) not in message  # the file is not at fault
    _same_prediction(tiny_model("real"), load_model(path, map_location="cpu")[0])


@pytest.mark.parametrize(
    "remap", [None, {"cuda:0": "cpu"}, lambda storage, location: storage], ids=["none", "dict", "function"]
)
def test_a_remapping_map_location_loads_the_model_on_the_cpu(tmp_path: Path, remap) -> None:
    path = save_model(tiny_model("real"), tmp_path / "m.pt")
    model, _ = load_model(path, map_location=remap)
    assert {p.device.type for p in model.parameters()} == {"cpu"}
    _same_prediction(tiny_model("real"), model)


def test_save_model_names_a_file_where_a_folder_goes(tmp_path: Path) -> None:
    notes = tmp_path / "notes"
    notes.write_text("the user's notes")
    for path in (notes / "m.pt", notes / "models" / "m.pt"):
        with pytest.raises(NotADirectoryError) as info:
            save_model(tiny_model("real"), path)
        assert str(info.value) == f"cannot write {path}: {notes} is a file, where a folder goes"
    assert notes.read_text() == "the user's notes" and sorted(tmp_path.iterdir()) == [notes]


@pytest.mark.parametrize("overwrite", [False, True])
def test_save_model_refuses_a_folder_at_its_path(tmp_path: Path, overwrite: bool) -> None:
    folder = tmp_path / "m.pt"
    folder.mkdir()
    with pytest.raises(IsADirectoryError, match=rf"^{re.escape(str(folder))} is a folder: save_model writes a file"):
        save_model(tiny_model("real"), folder, overwrite=overwrite)
    assert list(tmp_path.iterdir()) == [folder] and not any(folder.iterdir())


def test_save_model_removes_the_temporary_a_killed_save_left(tmp_path: Path) -> None:
    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".m.pt.tmp-{int(done.stdout)}"  # the process that wrote it has ended
    live = tmp_path / f".m.pt.tmp-{os.getppid()}"  # a save running in another process
    other = tmp_path / f".n.pt.tmp-{int(done.stdout)}"  # another file's
    for tmp in (stale, live, other):
        tmp.write_bytes(b"partial")
    path = save_model(tiny_model("real"), tmp_path / "m.pt")
    assert sorted(tmp_path.iterdir()) == sorted([path, live, other])


def test_a_directory_is_not_a_checkpoint(tmp_path: Path) -> None:
    with pytest.raises(IsADirectoryError, match=r"is a directory, not a checkpoint file"):
        load_model(tmp_path)


def test_a_stored_config_is_size_checked_before_the_model_is_built(tmp_path: Path, monkeypatch) -> None:
    import copy

    from unicorn.io.checkpoints import MAX_MODEL_PARAMS, ModelTooLargeError
    from unicorn.io.serialization import atomic_save
    from unicorn.model import Unicorn, count_parameters

    model = tiny_model("real", seed=1)
    config = copy.deepcopy(model.config)
    # the oracle: the built model's networks (template, renderer, losses hold no size of their own)
    networks = [model.encoders, model.shape, model.texture, model.background, model.pose, model.scale]
    assert count_parameters(config) == sum(t.numel() for m in networks for t in [*m.parameters(), *m.buffers()])
    config["encoder"]["width"] = 8192  # ~10^11 parameters: hundreds of GB if it were built
    path = atomic_save({"format": "unicorn-model", "config": config, "state_dict": {}, "info": {}}, tmp_path / "w.pt")
    built = []
    monkeypatch.setattr(Unicorn, "__init__", lambda *a, **k: built.append(1))
    with pytest.raises(ModelTooLargeError, match=r"encoder\.width=8192.*UNICORN_MAX_MODEL_PARAMS"):
        load_model(path)
    assert not built and count_parameters(config) > MAX_MODEL_PARAMS
    monkeypatch.undo()
    # the limit can be changed: a low one refuses even the tiny model
    monkeypatch.setenv("UNICORN_MAX_MODEL_PARAMS", "1000")
    with pytest.raises(ModelTooLargeError, match="above the limit of 1,000"):
        load_model(save_model(model, tmp_path / "m.pt"))


def test_only_training_checkpoints_resume_the_others_name_init_from(tmp_path: Path) -> None:
    from unicorn.io.checkpoints import NotATrainingCheckpointError, check_training_checkpoint

    check_training_checkpoint({"pytorch-lightning_version": "2.5", "state_dict": {}}, "run.ckpt")
    for data, kind in [
        ({"model_state": {}, "model_kwargs": {}}, "a released UNICORN model"),
        ({"format": "unicorn-model", "config": {}, "state_dict": {}}, "a unicorn.io.save_model file"),
        ({"weights": 1}, "not a unicorn-train checkpoint"),
    ]:
        with pytest.raises(NotATrainingCheckpointError, match=rf"m\.pkl is {kind}.*use init_from=m\.pkl"):
            check_training_checkpoint(data, "m.pkl")


def test_init_weights_copies_every_weight_or_refuses(tmp_path: Path) -> None:
    from unicorn.io.checkpoints import init_weights
    from unicorn.model import Unicorn

    source = tiny_model("real", seed=1)
    path = save_model(source, tmp_path / "m.pt")
    target = Unicorn(source.config)
    info = init_weights(target, path)
    assert info.format == "plain"
    for key, value in source.state_dict().items():
        assert torch.equal(target.state_dict()[key], value), key
    other = Unicorn(source.config, shape={"code_dim": source.config["shape"]["code_dim"] * 2})
    with pytest.raises(CheckpointError, match=r"init_from: the weights of .* do not fit the configured model"):
        init_weights(other, path)


def test_init_weights_keeps_the_runs_own_background_colour(tmp_path: Path) -> None:
    from unicorn.io.checkpoints import init_weights
    from unicorn.model import Unicorn

    source = tiny_model("real", seed=1)  # white behind the mesh
    path = save_model(source, tmp_path / "m.pt")
    target = Unicorn(source.config, renderer={"background_color": (0.0, 0.5, 0.0)})
    init_weights(target, path)
    assert tuple(target.config["renderer"]["background_color"]) == (0.0, 0.5, 0.0)
    assert torch.equal(target.renderer.background_color, torch.tensor([0.0, 0.5, 0.0]))
    for key, value in source.state_dict().items():
        if not key.startswith("renderer."):
            assert torch.equal(target.state_dict()[key], value), key


def test_save_model_keeps_info_load_model_can_read_back_and_names_what_it_cannot(tmp_path):
    import numpy as np

    model = tiny_model("real")
    _, info = load_model(save_model(model, tmp_path / "first.pt", epoch=np.int64(2)))
    path = save_model(model, tmp_path / "m.pt", info=info, note=tmp_path / "notes.txt", scores=(np.float32(0.5), 1))
    _, again = load_model(path)  # no UnsafeCheckpointError: only plain values were written
    assert again.extra["info"]["path"] == str(tmp_path / "first.pt") and again.extra["info"]["epoch"] == 2
    assert again.extra["note"] == str(tmp_path / "notes.txt") and again.extra["scores"] == [0.5, 1]
    with pytest.raises(TypeError, match=r"^save_model: extra.model is a Unicorn, which load_model would refuse"):
        save_model(model, tmp_path / "bad.pt", extra={"model": model})
    assert not (tmp_path / "bad.pt").exists()
