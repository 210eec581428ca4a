"""Values the types let through but the run cannot use: each is a one-line ``ConfigError`` naming the setting, from
``validate``, before anything is built, generated or written."""

from __future__ import annotations

import pytest

from tests.support.training import compose_config
from unicorn.config import ConfigError, validate

SYNTHETIC = ["experiment=synthetic"]
CUB = ["experiment=cub", "dataset.root=/data/cub_200"]

#: (id, overrides, the error's pattern)
CASES = [
    (
        "renderer-size",
        [*SYNTHETIC, "+renderer.image_size=0"],
        r"^renderer.image_size \(0\) differs from dataset.img_size \(32\): the renderer renders at the model's image "
        r"size; leave renderer.image_size out$",
    ),
    (
        "models-huge",
        [*SYNTHETIC, "dataset.synthetic.n_models=1000000000000"],
        r"n_models must be a whole number >= 3 and <= 100,000",
    ),
    ("models-text", [*SYNTHETIC, "dataset.synthetic.n_models=abc"], r"n_models must be a whole number .* got 'abc'"),
    (
        "synthetic-seed",
        [*SYNTHETIC, "dataset.synthetic.seed=-1"],
        r"dataset.synthetic: seed must be a whole number >= 0",
    ),
    (
        "no-views",
        [*SYNTHETIC, "+dataset.synthetic.n_views=0"],
        r"n_views must be a whole number >= 1 and <= 10,000, got 0",
    ),
    (
        "views-huge",
        [*SYNTHETIC, "+dataset.synthetic.n_views=1000000000000"],
        r"n_views must be a whole number >= 1 and <= 10,000, got 1000000000000",
    ),
    (
        "size-text",
        [*SYNTHETIC, "dataset.synthetic.image_size=abc"],
        r"image_size must be a whole number >= 1, got 'abc'",
    ),
    ("mode", [*SYNTHETIC, "dataset.synthetic.mode=bogus"], r"mode must be 'nmr' or 'wild', got 'bogus'"),
    # an empty list wrote an empty dataset into the shared cache, then blamed its metadata.yaml
    ("no-categories", [*SYNTHETIC, "dataset.categories=[]"], r"dataset.synthetic: no synthetic category given"),
    ("no-stages", [*SYNTHETIC, "model.stages.texture=[]"], r"model.stages.texture needs 4 sizes .*, got \[\]$"),
    (
        "memory-huge",
        [*SYNTHETIC, "model.loss.memory_size=2000000000"],
        r"model.loss.memory_size must be in \[1, 100000\], got 2000000000",
    ),
    (
        "mean-shape-huge",
        [*SYNTHETIC, "callbacks.heldout.mean_shape_iterations=1000000000"],
        r"callbacks.heldout.mean_shape_iterations must be in \[0, 100000\], got 1000000000",
    ),
    ("category", [*SYNTHETIC, "dataset.categories=unicorns"], r"unknown synthetic category 'unicorns'"),
    # the whole model cast: its first render failed on float32 pose tensors beside bfloat16 ones
    (
        "precision-cast",
        [*SYNTHETIC, "trainer.precision=bf16-true"],
        r"^trainer.precision=bf16-true casts the whole model, .* use bf16-mixed \(or 16-mixed on CUDA\)",
    ),
    ("precision-cast-16", [*SYNTHETIC, "trainer.precision=16-true"], r"^trainer.precision=16-true casts the whole"),
    ("unknown-setting", [*SYNTHETIC, "+dataset.synthetic.colour=red"], r"unknown setting 'colour'"),
    ("roll-in-nmr", [*SYNTHETIC, "+dataset.synthetic.roll=5"], r"roll=5 is for the wild mode"),
    ("dataset-seed", [*SYNTHETIC, "dataset.seed=-1"], r"dataset.seed must be a whole number in \[0, 4294967295\]"),
    (
        "focal-length",
        [*CUB, "~renderer.camera.fov", "+renderer.camera.focal_length=0"],
        r"^renderer.camera.focal_length must be a finite number > 0",
    ),
    ("fov", [*CUB, "renderer.camera.fov=0"], r"^renderer.camera.fov must be in \(0, 180\) degrees, got 0.0$"),
    # one grey level, or a colour's name, as the key's own error (not "'float' object is not iterable")
    (
        "background-grey",
        [*SYNTHETIC, "renderer.background_color=0.5"],
        r"^renderer.background_color must be three numbers in \[0, 1\] \(RGB\), got 0.5$",
    ),
    ("background-name", [*SYNTHETIC, "renderer.background_color=white"], r"\(RGB\), got white$"),
    ("background-null", [*SYNTHETIC, "renderer.background_color=null"], r"\(RGB\), got None$"),
    # a value of the wrong type: OmegaConf's message in one line, named by its key
    (
        "seed-float",
        [*SYNTHETIC, "seed=1.5"],
        r"^invalid training config: seed: Value '1.5' of type 'float' could not be converted to Integer$",
    ),
    (
        "steps-text",
        [*SYNTHETIC, "trainer.max_steps=abc"],
        r"^invalid training config: trainer.max_steps: Value 'abc' of type 'str' could not be converted to Integer$",
    ),
    ("translation-pair", [*CUB, "model.pose.T_range=[0.1,0.2]"], r"T_range must be a finite number or 3 of them"),
    (
        "translation-null",
        [*CUB, "model.pose.T_range=null"],
        r"T_range must be a finite number or 3 of them .* got None",
    ),
    ("translation-negative", [*CUB, "model.pose.T_range=-0.1"], r"T_range must be .* in \[0, inf\)"),
    ("scale-flips", [*CUB, "model.pose.scale_range=2"], r"scale_range must be .* in \[0, 1\) \(scales 1 \+- it"),
    ("behind-the-camera", [*CUB, "model.pose.prior_translation=[0,0,0]"], r"prior_translation's z \(0\) must exceed"),
    ("image-size-not-a-power-of-2", [*CUB, "dataset.img_size=48"], r"model.image_size must be a power of 2 .*got 48"),
    ("task-name-path", [*SYNTHETIC, "task_name=../x"], r"task_name must be a folder name, not a path .* got '\.\./x'"),
    ("task-name-empty", [*SYNTHETIC, "task_name=''"], r"task_name must be a folder name"),
    ("lr-drop-to-zero", [*SYNTHETIC, "optim.lr_drop_gamma=0"], r"optim.lr_drop_gamma .*in \[1e-06, 1\]"),
    # an unset shell variable (dataset.root=$DATA): the current folder, where the synthetic set was generated
    ("root-empty", [*SYNTHETIC, "dataset.root="], r"^dataset.root is empty: give the folder of its data"),
    ("root-blank", [*CUB, "dataset.root=' '"], r"^dataset.root is empty"),
    # the run's folder ${paths.log_dir}/${task_name}/runs/<time> at the file system's root
    ("log-dir-empty", [*SYNTHETIC, "paths.log_dir="], r"^paths.log_dir is empty: give the folder the runs go under"),
    ("init-from-empty", [*SYNTHETIC, "init_from="], r"^init_from is empty: name a weights file"),
    # UNICORN_CACHE= (exported, empty): the synthetic set at /synthetic_32px
    (
        "no-checkpoint-kept",
        [*SYNTHETIC, "callbacks.checkpoint.keep=0", "callbacks.checkpoint.save_last=false"],
        r"^callbacks.checkpoint.keep=0 with save_last=false keeps no checkpoint: the trained weights would be lost",
    ),
    ("cache-empty", [*SYNTHETIC, "paths.cache_dir="], r"^paths.cache_dir is empty: set UNICORN_CACHE to a folder"),
    ("vgg16-empty", [*SYNTHETIC, "paths.vgg16="], r"^paths.vgg16 is empty: set UNICORN_VGG16"),
    ("deterministic", [*SYNTHETIC, "trainer.deterministic=bogus"], r"trainer.deterministic must be true, false, warn"),
    ("another-renderers-option", [*SYNTHETIC, "renderer=hard"], r"drop them with ~renderer\.faces_per_pixel$"),
    # the one-category datasets built without reading it: a run on the wrong data would not say so
    (
        "categories-of-one-category-data",
        [*CUB, "+dataset.categories=bird"],
        r"^dataset.categories='bird', but dataset cub_200 holds one category and would ignore it: drop it "
        r"\(dataset.categories=null\)$",
    ),
    (
        "an-experiments-categories-on-a-folder",
        [*SYNTHETIC, "dataset=folder", "dataset.root=/photos"],
        r"^dataset.categories='car', but dataset folder holds one category",
    ),
    # cub's crop jitter after the dataset group is switched: refused only when the data was read, naming no key
    (
        "an-experiments-options-on-a-folder",
        [*CUB, "dataset=folder", "dataset.root=/photos"],
        r"^dataset.options \['jitter'\] are not taken by dataset folder \(its options: \['extensions'\]\); an "
        r"experiment may set them for another dataset: drop them with ~dataset.options.jitter$",
    ),
    (
        "an-option-the-dataset-lacks",
        [*CUB, "+dataset.options.tag=horse"],
        r"^dataset.options \['tag'\] are not taken by dataset cub_200 \(its options: \['augment', 'eval_size', "
        r"'jitter'\]\);.* drop them with ~dataset.options.tag$",
    ),
    # the model builds its perspective camera whatever the node names: another class was silently not used
    (
        "camera-class",
        [*CUB, "renderer.camera._target_=my_cameras.Orthographic"],
        r"^renderer.camera._target_=my_cameras.Orthographic is not supported: the model's camera is "
        r"unicorn.geometry.cameras.PerspectiveCamera",
    ),
    # Lightning compared the text with a number: "'<=' not supported between instances of 'int' and 'str'"
    (
        "limit-val-text",
        [*SYNTHETIC, "trainer.limit_val_batches=abc"],
        r"^trainer.limit_val_batches must be a number of batches >= 0 or a fraction in \[0, 1\], got 'abc'$",
    ),
    (
        "limit-val-negative",
        [*SYNTHETIC, "trainer.limit_val_batches=-1"],
        r"^trainer.limit_val_batches must be .*got -1$",
    ),
    ("limit-val-fraction", [*SYNTHETIC, "trainer.limit_val_batches=1.5"], r"^trainer.limit_val_batches .*got 1.5$"),
]


@pytest.mark.parametrize("overrides, message", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_a_value_the_run_cannot_use_is_one_config_error(tmp_path, overrides, message) -> None:
    with pytest.raises(ConfigError, match=message) as info:
        validate(compose_config([*overrides, f"paths.output_dir={tmp_path}"]))
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "overrides",
    [
        SYNTHETIC,
        ["experiment=synthetic_wild"],
        [*SYNTHETIC, "dataset.synthetic.mode=wild", "+dataset.synthetic.roll=0", "+dataset.synthetic.shift=0"],
        [*SYNTHETIC, "dataset.categories=[car,chair]", "+dataset.synthetic.background_kinds=[solid]",
         "dataset.synthetic.mode=wild"],
        CUB,
        [*SYNTHETIC, "dataset=folder", "dataset.root=/photos", "dataset.categories=null"],
        [*SYNTHETIC, "renderer=hard", "~renderer.faces_per_pixel"],
        [*SYNTHETIC, "+renderer.image_size=32"],  # the images' size: accepted
        [*CUB, "dataset=folder", "dataset.root=/photos", "~dataset.options.jitter"],
        [*SYNTHETIC, "trainer.limit_val_batches=4"],
        [*SYNTHETIC, "trainer.limit_val_batches=0.25"],
        [*SYNTHETIC, "trainer.limit_val_batches=2.0"],  # Lightning's whole float: 2 batches
    ],
)  # fmt: skip
def test_the_documented_settings_pass(tmp_path, overrides) -> None:
    validate(compose_config([*overrides, f"paths.output_dir={tmp_path}"]))
