"""``Registry``: register by name, refuse a second registration, one error for an unknown name, options checked."""

from __future__ import annotations

from importlib.metadata import EntryPoint
from string import Template

import pytest

import unicorn.registry as registry
from unicorn.data.registry import build_dataset
from unicorn.errors import UserError
from unicorn.evaluation import get_protocol
from unicorn.model.compositing import build_compositing
from unicorn.model.config import LOSS_KEYS
from unicorn.objectives.perceptual import build_perceptual
from unicorn.objectives.pose_objectives import AssignedLoss, build_pose_objective
from unicorn.objectives.viewpoint import build_viewpoint_supervision
from unicorn.registry import Registry, UnknownNameError, UnknownOptionError
from unicorn.render import build_renderer


def _things() -> Registry[tuple]:
    things: Registry[tuple] = Registry("thing", key="loss.thing")

    @things.register("pair")
    def pair(a: int, b: int = 2) -> tuple:
        return (a, b)

    return things


def test_register_list_get_and_build() -> None:
    things = _things()
    assert things.names() == ["pair"] and "pair" in things and list(things) == ["pair"] and len(things) == 1
    assert things.build("pair", {"a": 1}) == (1, 2)
    assert things.get("pair")(3, 4) == (3, 4)
    things.add("pair", things.get("pair"))  # the same entry again: nothing changes
    with pytest.raises(ValueError, match=r"thing 'pair' is already registered"):
        things.register("pair")(lambda: None)
    with pytest.warns(UserWarning, match="replacing thing 'pair'"):
        things.add("pair", lambda: "new", overwrite=True)
    assert things.build("pair") == "new"
    things.remove("pair")
    assert things.names() == []


def test_an_unknown_name_is_one_user_error_listing_the_known_ones() -> None:
    with pytest.raises(UnknownNameError, match=r"unknown loss.thing 'trio'; known: \['pair'\]") as err:
        _things().build("trio")
    assert isinstance(err.value, UserError) and isinstance(err.value, ValueError)


def test_unknown_options_are_refused_unless_they_are_keys_of_the_group() -> None:
    things = _things()
    with pytest.raises(UnknownOptionError, match=r"thing 'pair' takes no option 'c'; its options: \['a', 'b'\]") as err:
        things.build("pair", {"a": 1, "c": 3})
    assert isinstance(err.value, TypeError) and isinstance(err.value, UserError)
    # a flat configuration group feeds several constructors, each taking its part: the group's other keys are left
    # out, a key of no one's is still refused
    assert things.build("pair", {"a": 1, "c": 3}, group_keys=("a", "b", "c")) == (1, 2)
    with pytest.raises(UnknownOptionError, match="no option 'typo'"):
        things.build("pair", {"a": 1, "typo": 3}, group_keys=("a", "b", "c"))


def test_a_base_class_is_enforced_and_values_can_be_registered() -> None:
    classes: Registry[type] = Registry("backend", base=Exception)
    with pytest.raises(TypeError, match="must be a subclass of Exception"):
        classes.add("x", object)
    values: Registry[int] = Registry("size")
    values.add("small", 1)
    assert values.get("small") == 1 and values.items() == [("small", 1)]
    with pytest.raises(ValueError, match="non-empty string"):
        values.add("", 2)


def _build_dataset(name: str, **options: object) -> object:
    return build_dataset(name, "train", "/nowhere", **options)


#: every family's build-by-name function, with a name that family has
FAMILIES = {
    "renderer": (build_renderer, "layered"),
    "dataset": (_build_dataset, "lsun"),
    "perceptual loss": (build_perceptual, "structural"),
    "pose_objective": (build_pose_objective, "expected"),
    "viewpoint": (build_viewpoint_supervision, "renders"),
}


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_every_family_refuses_an_unknown_option_naming_it(family: str) -> None:
    build, name = FAMILIES[family]
    with pytest.raises(UnknownOptionError, match=rf"'{name}' takes no option 'colour'; its options: \[") as err:
        build(name, colour=1)  # refused before anything is built or read
    assert "\n" not in str(err.value) and isinstance(err.value, UserError)


@pytest.mark.parametrize(
    ("lookup", "message"),
    [
        (lambda: build_renderer("nope"), r"unknown renderer 'nope'; known: \['hard', 'layered', 'softras'"),
        (lambda: _build_dataset("nope"), r"unknown dataset 'nope'; known: \['compcars', 'cub_200', 'folder', 'lsun'"),
        (lambda: get_protocol("nope"), r"unknown protocol 'nope'; known: \['cub', 'images', 'p3d', 'shapenet'\]"),
        (lambda: build_perceptual("nope"), r"unknown perceptual loss 'nope'; known: \['structural', 'vgg'\]"),
        (lambda: build_pose_objective("nope"), r"unknown pose_objective 'nope'; known: \['assigned', 'assigned_best'"),
        (lambda: build_viewpoint_supervision("nope"), r"unknown viewpoint 'nope'; known: \['renders'\]"),
        (lambda: build_compositing("nope"), r"unknown compositing 'nope'; known: \['direct', 'reference'\]"),
    ],
)
def test_every_family_names_the_known_ones_for_an_unknown_name(lookup, message: str) -> None:
    with pytest.raises(UnknownNameError, match=message) as err:
        lookup()
    assert "\n" not in str(err.value)


def test_the_loss_group_feeds_each_constructor_its_part() -> None:
    loss = {key: None for key in LOSS_KEYS}
    assert isinstance(build_pose_objective("assigned", **{**loss, "assignment_weight": 0.5}), AssignedLoss)
    with pytest.raises(UnknownOptionError, match="no option 'assignment_wieght'"):
        build_pose_objective("assigned", **loss, assignment_wieght=0.5)


def test_entry_points_register_on_first_lookup_and_a_broken_one_warns(monkeypatch) -> None:
    points = [
        EntryPoint("template", "string:Template", "unicorn.things"),
        EntryPoint("missing", "string:NoSuchThing", "unicorn.things"),
    ]
    monkeypatch.setattr(registry, "entry_points", lambda group: points if group == "unicorn.things" else [])
    things: Registry[type] = Registry("thing", base=Template, entry_points="unicorn.things")
    with pytest.warns(UserWarning, match=r"could not load thing entry point 'missing' \(string:NoSuchThing\)"):
        assert things.names() == ["template"]
    assert things.build("template", {"template": "$x"}).substitute(x=1) == "1"


def test_an_entry_point_named_like_a_registered_entry_is_not_used_and_says_so(monkeypatch) -> None:
    class Mine(Template):
        pass

    points = [
        EntryPoint("template", "string:Template", "unicorn.things"),  # the entry registered: nothing to say
        EntryPoint("taken", "string:Template", "unicorn.things"),  # another class under a taken name
    ]
    monkeypatch.setattr(registry, "entry_points", lambda group: points if group == "unicorn.things" else [])
    things: Registry[type] = Registry("thing", base=Template, entry_points="unicorn.things")
    things.add("template", Template)
    things.add("taken", Mine)
    with pytest.warns(
        UserWarning, match=r"entry point 'taken' \(string:Template\) is not used: thing 'taken' is"
    ) as seen:
        assert things.get("taken") is Mine
    assert len(seen) == 1 and "give the entry point another name" in str(seen[0].message)


def test_a_taken_name_is_described_by_its_type_not_its_whole_value() -> None:
    values: Registry[object] = Registry("spec")
    values.add("a", Template("x"))
    with pytest.raises(ValueError, match=r"^spec 'a' is already registered \(Template\); pass overwrite=True"):
        values.add("a", Template("y"))


def test_an_entry_without_the_methods_of_its_family_is_refused() -> None:
    family: Registry[object] = Registry("objective", methods=("pose_terms",))

    class Complete:
        def pose_terms(self) -> None: ...

    class Incomplete:
        def __call__(self) -> None: ...

    family.add("complete", Complete)
    with pytest.raises(registry.IncompleteEntryError, match=r"^objective 'no' \(.*Incomplete\) has no pose_terms; "):
        family.add("no", Incomplete)  # a class: when it is registered
    family.add("factory", lambda: Incomplete())
    with pytest.raises(registry.IncompleteEntryError, match=r"objective 'factory' \(.*Incomplete\) has no pose_terms"):
        family.build("factory")  # another constructor: what it builds
    assert isinstance(family.build("complete"), Complete) and issubclass(registry.IncompleteEntryError, UserError)


@pytest.mark.parametrize(
    "module, register",
    [
        ("unicorn.objectives.pose_objectives", "register_pose_objective"),
        ("unicorn.objectives.perceptual", "register_perceptual"),
        ("unicorn.objectives.viewpoint", "register_viewpoint_supervision"),
        ("unicorn.model.compositing", "register_compositing"),
    ],
)
def test_every_register_function_replaces_a_name_only_when_asked(module: str, register: str, monkeypatch) -> None:
    import importlib

    mod = importlib.import_module(module)
    family = next(v for v in vars(mod).values() if isinstance(v, Registry))
    monkeypatch.setattr(family, "_entries", dict(family._loaded()))  # put back after the test
    name = family.names()[0]

    class Replacement:
        def __call__(self, *args, **kwargs): ...
        def pose_terms(self, *args): ...
        def shape_pose(self, *args): ...
        def active(self, iteration): ...

    with pytest.raises(ValueError, match=rf"{name!r} is already registered .*pass overwrite=True"):
        getattr(mod, register)(name)(Replacement)
    with pytest.warns(UserWarning, match=f"replacing .*{name!r}"):
        getattr(mod, register)(name, overwrite=True)(Replacement)
    assert family.get(name) is Replacement


def test_plugins_are_imported_once_from_the_variable_and_the_entry_points(tmp_path, monkeypatch) -> None:
    (tmp_path / "probe_plugin_a.py").write_text(
        "import unicorn.registry as r\nr.imported = [*getattr(r, 'imported', []), 'a']\n"
    )
    (tmp_path / "probe_plugin_b.py").write_text(
        "import unicorn.registry as r\nr.imported = [*getattr(r, 'imported', []), 'b']\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv(registry.PLUGINS_ENV, " probe_plugin_a , ")
    points = [
        EntryPoint("b", "probe_plugin_b", registry.PLUGIN_GROUP),
        EntryPoint("broken", "probe_plugin_missing", registry.PLUGIN_GROUP),
    ]
    monkeypatch.setattr(registry, "entry_points", lambda group: points if group == registry.PLUGIN_GROUP else [])
    monkeypatch.setattr(registry, "_plugins_loaded", False)
    monkeypatch.setattr(registry, "imported", [], raising=False)
    with pytest.warns(UserWarning, match=r"could not load the unicorn.plugins entry point 'broken'"):
        registry.load_plugins()
    registry.load_plugins()  # once
    assert registry.imported == ["a", "b"]


def test_a_plugin_module_that_cannot_be_imported_is_one_error_naming_it(monkeypatch) -> None:
    monkeypatch.setenv(registry.PLUGINS_ENV, "probe_no_such_module")
    monkeypatch.setattr(registry, "_plugins_loaded", False)
    with pytest.raises(registry.PluginError, match=r"^UNICORN_PLUGINS: cannot import 'probe_no_such_module': Module"):
        registry.load_plugins()
    assert isinstance(registry.PluginError("x"), UserError)


def test_a_dataset_and_a_renderer_registered_after_import_are_accepted_by_the_training_config(tmp_path) -> None:
    from tests.support.training import compose_config
    from unicorn.config import validate
    from unicorn.config.build import model_config
    from unicorn.data.registry import DATASETS, DatasetSpec, list_datasets, register_dataset
    from unicorn.render import LayeredRenderer, register_renderer, unregister_renderer

    class KeywordsRenderer(LayeredRenderer):  # takes any option and passes it on
        def __init__(self, power: float = 1.0, **options) -> None:
            super().__init__(**options)
            self.power = power

    register_dataset("probe_objects", DatasetSpec(DATASETS.get("folder").build, 5, "images"))
    register_renderer("probe_keywords")(KeywordsRenderer)
    try:
        assert "probe_objects" in list_datasets()
        cfg = compose_config(
            ["dataset=folder", "dataset.name=probe_objects", "dataset.root=/data/mine", "renderer.name=probe_keywords",
             "+renderer.power=2.0", f"paths.output_dir={tmp_path}"]
        )  # fmt: skip
        typed = validate(cfg)
        assert model_config(typed)["renderer"]["options"]["power"] == 2.0
    finally:
        DATASETS.remove("probe_objects")
        unregister_renderer("probe_keywords")
