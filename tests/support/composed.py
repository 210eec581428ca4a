"""The composed training configs of the shipped presets, as recorded in ``tests/fixtures/composed_configs.yaml``.

Each case is a command line (overrides of ``conf/train.yaml``); its record is the validated config (one flattened
key per line, interpolations unresolved) or the one-line error the command gives: in full for the first case
(``train.yaml`` alone), as its differences from the first for the others. Run ``python -m tests.support.composed`` to
write the record again after a deliberate change of ``conf/`` or of the schema, and read its diff.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

RECORD = Path(__file__).resolve().parents[1] / "fixtures" / "composed_configs.yaml"
#: a run folder for the compositions (``${hydra:runtime.output_dir}`` only resolves inside a run)
_OUTPUT_DIR = "paths.output_dir=OUT"
#: the value recorded for a key of the first case that another case does not have
ABSENT = "(absent)"
#: the first case: conf/train.yaml with no overrides
BASE = "train.yaml"


def _names(group: str) -> list[str]:
    from unicorn.resources import config_dir

    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


def cases() -> list[str]:
    """The recorded command lines: train.yaml alone, every experiment, three experiments with every model size,
    every option of the other groups, every family with every model size."""
    found = [BASE, *(f"experiment={name}" for name in _names("experiment"))]
    found += [f"experiment={e} model={m}" for e in ("cub", "shapenet_chair", "synthetic") for m in _names("model")]
    for group in ("dataset", "model", "renderer", "schedule", "trainer", "logger", "callbacks", "paths"):
        found += [f"{group}={name}" for name in _names(group)]
    found += [f"+family={f} model={m}" for f in _names("family") for m in _names("model")]
    return found


def _flatten(node: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(node, dict) or not node:
        return {prefix[:-1]: node}
    flat: dict[str, Any] = {}
    for key, value in node.items():
        flat.update(_flatten(value, f"{prefix}{key}."))
    return flat


def composed_settings(case: str) -> dict[str, Any]:
    """The validated config of one command line, flattened (``group.key``: value, interpolations unresolved), or
    ``{"error": message}``."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from unicorn.config import ConfigError, validate
    from unicorn.resources import config_dir

    with initialize_config_dir(config_dir=str(config_dir()), version_base="1.3"):
        overrides = [] if case == BASE else case.split()
        composed = compose("train", overrides=[*overrides, _OUTPUT_DIR])
    try:
        return _flatten(OmegaConf.to_container(validate(composed), resolve=False))
    except ConfigError as err:
        return {"error": str(err)}


def difference(settings: dict[str, Any], base: dict[str, Any]) -> dict[str, Any]:
    """``settings`` as its differences from ``base``: changed or added keys, and removed ones as :data:`ABSENT`
    (an error's record is the error)."""
    if "error" in settings:
        return settings
    changed = {key: value for key, value in settings.items() if key not in base or base[key] != value}
    return dict(sorted({**changed, **{key: ABSENT for key in base if key not in settings}}.items()))


class _Dumper(yaml.SafeDumper):
    """One key per line, lists on the key's line."""


_Dumper.add_representer(list, lambda d, v: d.represent_sequence("tag:yaml.org,2002:seq", v, flow_style=True))
_Dumper.add_representer(dict, lambda d, v: d.represent_mapping("tag:yaml.org,2002:map", v, flow_style=False))


def recorded() -> dict[str, dict[str, Any]]:
    """The record: the first case (train.yaml alone) in full, every other one as its :func:`difference` from it."""
    return yaml.safe_load(RECORD.read_text(encoding="utf-8"))


def write_record() -> None:
    """Write the record of every case (:func:`cases`) to :data:`RECORD`."""
    base_case, *others = cases()
    base = composed_settings(base_case)
    record = {base_case: dict(sorted(base.items()))}
    record.update({case: difference(composed_settings(case), base) for case in others})
    text = yaml.dump(record, Dumper=_Dumper, sort_keys=False, width=120)
    header = "# Written by `python -m tests.support.composed` (tests/config/test_composed_configs.py reads it).\n"
    RECORD.write_text(header + text, encoding="utf-8")


if __name__ == "__main__":
    write_record()
