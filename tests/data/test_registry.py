"""The dataset registry: names, splits, validation subsets; no Lightning in ``unicorn.data``."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import unicorn.data.synthetic.writer as writer
from unicorn.cli.eval import build_parser
from unicorn.data import DatasetNotFoundError
from unicorn.data.registry import (
    DATASET_NAMES,
    build_dataset,
    dataset_root,
    dataset_spec,
    list_datasets,
    prepare_dataset,
    val_indices,
)
from unicorn.evaluation import protocol_for
from unicorn.registry import UnknownNameError, UnknownOptionError

#: every dataset a user can name (README, docs/datasets.md), in the order the commands list them, with the
#: reference's validation subset size and the evaluation protocol that scores it
EXPECTED_DATASETS = {
    "shapenet_nmr": (32, "shapenet"),
    "synthetic": (32, "shapenet"),
    "cub_200": (5, "cub"),
    "p3d_car": (5, "p3d"),
    "compcars": (5, "images"),
    "lsun": (5, "images"),
    "folder": (5, "images"),
}


def test_val_indices_reference_sizes_capped() -> None:
    assert val_indices("shapenet_nmr", 100) == list(range(32))
    assert val_indices("shapenet_nmr", 3) == [0, 1, 2]
    assert val_indices("lsun", 100) == list(range(17, 22))
    assert val_indices("lsun", 10) == list(range(5))
    cub = val_indices("cub_200", 50)
    assert len(cub) == 5 and cub == val_indices("cub_200", 50) and cub != list(range(5))
    assert val_indices("folder", 2) == [0, 1]


@pytest.mark.parametrize("n", [7, 2874])
def test_cub_validation_images_are_the_references(n: int) -> None:
    """CUB validates on the reference's images: the first 5 of its records after its shuffle, which seeds NumPy's
    global generator with 123 and shuffles the array of records in place."""
    records = np.empty(n, dtype=object)
    records[:] = [{"id": i} for i in range(n)]
    state = np.random.get_state()  # noqa: NPY002 (the reference's legacy global generator, put back after)
    try:
        np.random.seed(123)  # noqa: NPY002
        np.random.shuffle(records)  # noqa: NPY002
    finally:
        np.random.set_state(state)  # noqa: NPY002
    assert val_indices("cub_200", n) == [r["id"] for r in records[:5]]


def test_errors() -> None:
    with pytest.raises(ValueError, match="split"):
        build_dataset("folder", "training", ".")
    with pytest.raises(ValueError, match="unknown dataset 'imagenet'"):
        build_dataset("imagenet", "train", ".")


def test_dataset_root(tmp_path: Path) -> None:
    assert dataset_root("cub_200", tmp_path) == tmp_path
    synthetic = dataset_root("synthetic", tmp_path, ["car", "chair"], {"mode": "wild", "n_models": 3})
    assert synthetic.parent == tmp_path and synthetic.name.startswith("wild_car+chair_n3_s0_")
    assert dataset_root("synthetic", tmp_path).name.startswith("nmr_chair_n200_s0_")  # the defaults


def test_data_does_not_import_lightning() -> None:
    code = "import sys, unicorn.data, unicorn.data.registry; print(sorted(m for m in sys.modules if 'lightning' in m))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_one_registry_names_every_dataset_for_training_evaluation_and_the_cli() -> None:
    help_text = next(a.help for a in build_parser()._actions if a.dest == "dataset")
    assert list(DATASET_NAMES) == list(EXPECTED_DATASETS) and sorted(EXPECTED_DATASETS) == list_datasets()
    assert all(name in help_text for name in DATASET_NAMES)
    assert {name: protocol_for(name) for name in DATASET_NAMES} == {
        name: protocol for name, (_, protocol) in EXPECTED_DATASETS.items()
    }
    # the validation subset each dataset gets from a split larger than it
    assert {name: len(val_indices(name, 1000)) for name in DATASET_NAMES} == {
        name: size for name, (size, _) in EXPECTED_DATASETS.items()
    }


def test_unknown_dataset_names_the_known_ones() -> None:
    with pytest.raises(UnknownNameError, match=r"unknown dataset 'imagenet'; known: \['compcars', 'cub_200', 'folder'"):
        build_dataset("imagenet", "train", "/nowhere")
    for lookup in (lambda: val_indices("imagenet", 10), lambda: dataset_root("imagenet", "/nowhere")):
        with pytest.raises(UnknownNameError, match="unknown dataset"):
            lookup()


def test_synthetic_data_is_generated_only_where_asked(tmp_path: Path, monkeypatch) -> None:
    generated = []
    monkeypatch.setattr(writer, "ensure_synthetic_dataset", lambda **options: generated.append(options) or tmp_path)
    monkeypatch.setenv("UNICORN_CACHE", str(tmp_path / "cache"))
    missing = tmp_path / "nonexistent" / "dir"
    with pytest.raises(DatasetNotFoundError, match=r"nonexistent/dir.*dataset\.synthetic\.generate=true"):
        prepare_dataset("synthetic", missing)
    assert not generated and not missing.exists()
    prepare_dataset("synthetic", None)  # the cache
    prepare_dataset("synthetic", tmp_path / "cache" / "synthetic_32px")  # a new folder in the cache
    prepare_dataset("synthetic", tmp_path)  # an existing folder
    prepare_dataset("synthetic", missing, synthetic={"generate": True})  # asked for
    assert [g["root"] for g in generated] == [None, tmp_path / "cache" / "synthetic_32px", tmp_path, missing]
    assert all("generate" not in g for g in generated)  # not a generator option


def test_each_dataset_takes_its_evaluation_options_and_refuses_others() -> None:
    for name in DATASET_NAMES:
        spec = dataset_spec(name)
        assert set(spec.eval_options) <= set(spec.options), name
        assert not {"root", "split", "img_size", "on_error"} & set(spec.options), name  # set by the registry
    assert dataset_spec("lsun").options == ("tag", "cleaned", "padding", "jitter")
    with pytest.raises(UnknownOptionError, match=r"dataset 'compcars' takes no option 'tag'; its options: \[\]"):
        build_dataset("compcars", "train", "/nowhere", tag="car")


def test_the_box_jitter_is_an_option_of_the_cropped_datasets(cub_root: Path, p3d_root: Path) -> None:
    assert "jitter" in dataset_spec("cub_200").options and "jitter" in dataset_spec("p3d_car").options
    assert build_dataset("cub_200", "train", cub_root).jitter == 0.05  # the reference's
    assert build_dataset("cub_200", "train", cub_root, jitter=0.0).jitter == 0.0
    assert build_dataset("p3d_car", "train", p3d_root).jitter == 0.1
    assert build_dataset("p3d_car", "train", p3d_root, jitter=0.0).jitter == 0.0


def test_a_dataset_entry_of_the_wrong_kind_is_refused_when_registered(monkeypatch) -> None:
    from unicorn.data.registry import DATASETS, DatasetSpec, register_dataset

    monkeypatch.setattr(DATASETS, "_entries", dict(DATASETS._loaded()))  # put back after the test
    shapenet = dataset_spec("shapenet_nmr")
    with pytest.raises(TypeError, match=r"^register_dataset\('blobs', spec\): spec must be a DatasetSpec"):
        register_dataset("blobs", shapenet.build)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^DatasetSpec\.options must be a tuple of option names, got 'n_items'$"):
        DatasetSpec(shapenet.build, 5, "images", "n_items")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^DatasetSpec\.protocol must be a protocol's name, got None$"):
        DatasetSpec(shapenet.build, 5, None)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match=r"^DatasetSpec\.build must be a function"):
        DatasetSpec("shapenet", 5, "images")  # type: ignore[arg-type]
    assert DatasetSpec(shapenet.build, 5, "images", ["n_items"]).options == ("n_items",)


@pytest.mark.parametrize("name", ["shapenet_nmr", "synthetic"])
def test_a_category_named_twice_is_refused(synth_nmr: Path, name: str) -> None:
    """A category given twice, by name or by name and synset, is a mistake: its models would be read twice."""
    from unicorn.data.images import DatasetError

    with pytest.raises(DatasetError, match=r"^category 'car' is named twice in categories \['car', 'car'\]; name"):
        build_dataset(name, "test", synth_nmr, categories=["car", "car"])
    with pytest.raises(DatasetError, match=r"^categories 'car' and '90000003' are one category \(synset 90000003\)"):
        build_dataset(name, "train", synth_nmr, categories=["car", "chair", "90000003"])
    assert len(build_dataset(name, "test", synth_nmr, categories=["car", "chair"])) == 2
    assert len(build_dataset(name, "test", synth_nmr, categories="car")) == 1


def test_a_folder_of_generated_datasets_given_as_the_synthetic_root_names_them(tmp_path: Path) -> None:
    """A training run's dataset.root (the parent of the generated datasets) is not the dataset: the message lists
    the datasets in it to give instead, not ShapeNet-NMR's download."""
    from unicorn.data.images import DatasetError

    cache = tmp_path / "synthetic_32px"  # a scratch cache, laid out as a training run leaves it
    names = ["nmr_car_n100_s0_v2", "nmr_chair_n100_s0_v2", "nmr_lamp_n100_s0_v2", "wild_car_n100_s0_v2"]
    for name in names:
        (cache / name).mkdir(parents=True)
        (cache / name / "synthetic.json").write_text("{}")
    (cache / ".nmr_mug_n100_s0_v2.tmp-host-1-ab").mkdir()  # a generation under way is not one
    (cache / "notes").mkdir()
    for split in ("train", "test"):
        with pytest.raises(DatasetError) as info:
            build_dataset("synthetic", split, cache)
        assert str(info.value) == (
            f"{cache} is a folder of generated synthetic datasets (as a training run's dataset.root is), not one: "
            f"give one of them as the root: {cache / names[0]}, {cache / names[1]}, {cache / names[2]} (and 1 more)"
        )
    (cache / names[3] / "synthetic.json").unlink()
    with pytest.raises(DatasetError, match=rf"root: {cache / names[0]}, {cache / names[1]}, {cache / names[2]}$"):
        build_dataset("synthetic", "test", cache)
    # an existing folder with neither: named as the generated dataset it should be, with where that comes from
    with pytest.raises(DatasetNotFoundError) as info:
        build_dataset("synthetic", "test", cache / "notes")
    message = str(info.value)
    assert message.startswith(f"generated synthetic dataset's metadata.yaml not found at {cache / 'notes'}/metadata")
    assert "$UNICORN_CACHE/synthetic_32px with +experiment=synthetic" in message and "NMR_Dataset.zip" not in message
