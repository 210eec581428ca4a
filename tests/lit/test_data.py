"""The LightningDataModule: splits, validation subsets, loaders, the training stream, Hydra configs."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf

from tests.support.training import compose_config
from unicorn.data.images import DatasetError
from unicorn.lit import StreamBatchSampler, UnicornDataModule
from unicorn.lit.data import MAX_AUTO_WORKERS, auto_num_workers, usable_cpus

CONF = Path(__file__).resolve().parents[2] / "conf" / "dataset"


def test_shapenet_datamodule_builds_splits(synth_nmr: Path) -> None:
    dm = UnicornDataModule(
        "shapenet_nmr", str(synth_nmr), categories=["chair", "car"], batch_size=4, num_workers=0, seed=1
    )
    dm.setup()
    assert len(dm.train_set) == 2 * 6 and len(dm.val_set) == 2 and len(dm.test_set) == 2
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (4, 3, 64, 64) and batch["R"].shape == (4, 3, 3) and batch["has_pose"].all()
    val = next(iter(dm.val_dataloader()))
    assert val["points"].shape[0] == 2 and val["points"].shape[-1] == 3
    # the training order follows the seed
    first = [next(iter(dm.train_dataloader()))["index"].tolist() for _ in range(2)]
    assert first[0] == first[1]


def test_synthetic_datamodule_generates_on_first_use(tmp_path: Path) -> None:
    synth = {
        "mode": "wild",
        "n_models": 3,
        "seed": 2,
        "n_views": 2,
        "n_points": 100,
        "image_size": 32,
        "supersample": 1,
        "progress": False,
    }
    dm = UnicornDataModule(
        "synthetic", str(tmp_path), categories="airplane", batch_size=2, num_workers=0, synthetic=synth
    )
    dm.prepare_data()
    assert (dm.dataset_root() / "synthetic.json").exists() and dm.dataset_root().parent == tmp_path
    dm.setup("fit")
    batch = next(iter(dm.train_dataloader()))
    assert batch["image"].shape == (2, 3, 32, 32)


def test_stream_seed_trains_on_the_resumable_stream(cub_root: Path, tmp_path: Path) -> None:
    dm = UnicornDataModule("cub_200", str(cub_root), batch_size=3, num_workers=0, stream_seed=5)
    dm.setup("fit")
    loader = dm.train_dataloader()
    assert isinstance(loader.batch_sampler, StreamBatchSampler) and loader.batch_sampler.seed == 5
    batches = iter(loader)
    expected = StreamBatchSampler(len(dm.train_set), 3, seed=5)
    for b in range(3):  # past the end of the 4 training images: the stream goes on
        assert next(batches)["index"].tolist() == [i for _, i in expected.batch_at(b)]
    empty = UnicornDataModule("folder", str(tmp_path), num_workers=0, stream_seed=0)
    empty.build = lambda split: []  # e.g. every image skipped as unreadable
    with pytest.raises(DatasetError, match="no training images"):  # a UserError: one line in the CLIs
        empty.setup("fit")


def test_cub_datamodule_val_subset(cub_root: Path) -> None:
    dm = UnicornDataModule("cub_200", str(cub_root), batch_size=2, num_workers=0)
    dm.setup()
    assert len(dm.train_set) == 4 and len(dm.val_set) == 5 and len(dm.test_set) == 3
    assert dm.train_set.augment and not dm.val_set.dataset.augment
    batch = next(iter(dm.val_dataloader()))
    assert batch["keypoints"].shape == (2, 15, 3) and batch["mask"].shape == (2, 1, 64, 64)


def test_p3d_datamodule_validates_on_train_images(p3d_root: Path) -> None:
    dm = UnicornDataModule("p3d_car", str(p3d_root), batch_size=2, num_workers=0)
    dm.setup()
    assert len(dm.val_set) == 3 and dm.val_set.dataset.split == "train" and not dm.val_set.dataset.augment
    assert "points" in dm.test_set[0]


def test_cache_items_gives_the_same_batches(synth_nmr: Path) -> None:
    kw = {"categories": "car", "batch_size": 4, "num_workers": 0, "stream_seed": 3}
    plain, cached = (UnicornDataModule("shapenet_nmr", str(synth_nmr), cache_items=c, **kw) for c in (False, True))
    for dm in (plain, cached):
        dm.setup()
    assert cached.train_set._items == {} and plain.train_set._items is None
    assert cached.val_set.dataset._items is None and cached.test_set._items is None  # read a few times only
    for _ in range(2):  # the second time from memory
        a, b = next(iter(plain.train_dataloader())), next(iter(cached.train_dataloader()))
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
        assert len(cached.train_set._items) == 4


def test_cache_items_refuses_augmented_data(cub_root: Path) -> None:
    dm = UnicornDataModule("cub_200", str(cub_root), num_workers=0, cache_items=True)
    with pytest.raises(ValueError, match="cache_items=true for cub_200 train: CUB200 augments its items"):
        dm.setup("fit")


def test_errors() -> None:
    with pytest.raises(ValueError, match="unknown dataset 'imagenet'"):
        UnicornDataModule("imagenet", "x")
    with pytest.raises(ValueError, match="needs a root"):
        UnicornDataModule("cub_200")


def test_auto_num_workers_follows_the_machine() -> None:
    assert auto_num_workers("cpu", cpus=64) == 0  # the training's threads use the cores
    assert auto_num_workers("cuda", cpus=16) == 15  # one core left for the training process
    assert auto_num_workers("cuda", cpus=16, processes=4) == 3
    assert auto_num_workers("cuda", cpus=2) == auto_num_workers("cuda", cpus=1) == 1
    assert auto_num_workers("cuda", cpus=256) == MAX_AUTO_WORKERS
    assert auto_num_workers("cuda") == max(1, min(MAX_AUTO_WORKERS, usable_cpus() - 1))


class _Strategy:
    def __init__(self, device: str) -> None:
        self.root_device = torch.device(device)


class _Trainer:
    """What the loaders read of a Lightning trainer."""

    global_step, global_rank, world_size = 0, 0, 1

    def __init__(self, device: str, num_devices: int = 1) -> None:
        self.strategy, self.num_devices = _Strategy(device), num_devices


@pytest.mark.filterwarnings("ignore:This DataLoader will create")  # 7 workers on this machine: never started
@pytest.mark.parametrize("device", ["cpu", "cuda"])
def test_loaders_choose_workers_and_pinning_from_the_training_device(cub_root: Path, device: str, monkeypatch) -> None:
    monkeypatch.setattr("unicorn.lit.data.usable_cpus", lambda: 16)
    dm = UnicornDataModule("cub_200", str(cub_root), batch_size=2, stream_seed=0)
    assert (dm.num_workers, dm.pin_memory) == ("auto", "auto")  # the defaults
    dm.trainer = _Trainer(device, num_devices=2)
    dm.setup("fit")
    workers, pin = (7, True) if device == "cuda" else (0, False)
    assert dm.loader_settings() == (workers, pin)
    for loader in (dm.train_dataloader(), dm.val_dataloader()):  # the stream and the plain loader
        assert (loader.num_workers, loader.pin_memory, loader.persistent_workers) == (workers, pin, workers > 0)
    given = UnicornDataModule("cub_200", str(cub_root), num_workers=3, pin_memory=False)
    given.trainer = _Trainer(device)
    assert given.loader_settings() == (3, False)
    assert UnicornDataModule("cub_200", str(cub_root), num_workers=None, pin_memory=None).num_workers == "auto"


def test_bad_loader_settings_are_refused(cub_root: Path, tmp_path: Path) -> None:
    from unicorn.config import ConfigError, validate

    for kw, message in [
        ({"num_workers": -1}, "num_workers must be a number >= 0, 'auto' or None"),
        ({"num_workers": "many"}, "num_workers must be a number >= 0"),
        ({"num_workers": True}, "num_workers must be a number >= 0"),
        ({"pin_memory": "yes"}, "pin_memory must be true or false, 'auto' or None"),
    ]:
        with pytest.raises(ValueError, match=message):
            UnicornDataModule("cub_200", str(cub_root), **kw)
    out = f"paths.output_dir={tmp_path}"
    for override in ("dataset.num_workers=auto", "dataset.num_workers=null", "dataset.num_workers=3"):
        validate(compose_config([override, out]))
    for override, message in [
        ("dataset.num_workers=-1", r"dataset\.num_workers must be >= 0, or auto"),
        ("dataset.num_workers=some", r"dataset\.num_workers must be >= 0, or auto \(chosen from the machine\)"),
        ("dataset.pin_memory=maybe", r"dataset\.pin_memory must be true, false or auto"),
    ]:
        with pytest.raises(ConfigError, match=message):
            validate(compose_config([override, out]))


@pytest.mark.parametrize("path", sorted(CONF.glob("*.yaml")), ids=lambda p: p.stem)
def test_hydra_configs_instantiate(path: Path, tmp_path: Path) -> None:
    # the dataset group as unicorn-train composes it: the preset over the schema's defaults
    cfg = compose_config([f"dataset={path.stem}", f"paths.output_dir={tmp_path}"]).dataset
    if OmegaConf.is_missing(cfg, "root"):
        cfg.root = str(tmp_path)
    dm = instantiate(cfg)
    assert isinstance(dm, UnicornDataModule) and dm.name == cfg.name
    assert dm.batch_size == 32 and isinstance(dm.seed, int)
    assert dm.categories is None or isinstance(dm.categories, (str, list))
    if dm.name == "shapenet_nmr":
        assert dm.categories == ["airplane"]
    torch.testing.assert_close(torch.tensor(dm.img_size), torch.tensor(64))


def test_loader_workers_outlive_a_signal_to_the_process_group(cub_root: Path) -> None:
    """Ctrl-C and a scheduler signal the whole group: the workers ignore it, the run's process stops cleanly."""
    import os
    import signal
    import time

    dm = UnicornDataModule("cub_200", str(cub_root), batch_size=2, num_workers=1, stream_seed=0)
    dm.setup("fit")
    batches = iter(dm.train_dataloader())
    next(batches)
    [worker] = batches._workers
    for signum in (signal.SIGTERM, signal.SIGINT):
        os.kill(worker.pid, signum)
    time.sleep(0.5)
    assert worker.is_alive()
    for _ in range(3):
        assert next(batches)["image"].shape[0] == 2
    del batches
