"""The template mesh's arguments: refused by the geometry functions that own them, in their one-line words."""

import pytest
import torch

from unicorn.model import TemplateMesh


@pytest.mark.parametrize("level", [2.5, True, 8, "3"])
def test_template_refuses_a_level_with_icosphere_s_message(level):
    # a level of 2.5 reaches icosphere as it is (int() would have built level 2 without a word)
    with pytest.raises(ValueError, match=rf"^icosphere level must be a whole number in \[0, 7\], got {level!r}$"):
        TemplateMesh(level=level)


def test_template_takes_a_whole_float_level():
    t = TemplateMesh(level=2.0)
    assert t.level == 2 and isinstance(t.level, int) and t.num_verts == TemplateMesh(level=2).num_verts == 162


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"scale": float("nan")}, r"^ellipsoid scale must be a finite number > 0, got nan$"),
        ({"scale": 0.0}, r"^ellipsoid scale must be a finite number > 0, got 0\.0$"),
        ({"axes": (1.0, 0.7)}, r"^ellipsoid axes must be three finite numbers > 0 .*, got \(1\.0, 0\.7\)$"),
        ({"axes": (1.0, float("nan"), 0.7)}, r"^ellipsoid axes must be three finite numbers > 0"),
        ({"bottom": float("nan")}, r"^ellipsoid bottom must be a number in \(0, 1\], got nan$"),
        ({"bottom": -1.0}, r"^ellipsoid bottom must be a number in \(0, 1\], got -1\.0$"),
    ],
)
def test_template_refuses_a_stretch_with_ellipsoid_s_message(kwargs, match):
    with pytest.raises(ValueError, match=match):
        TemplateMesh(level=1, **kwargs)


def test_template_records_its_arguments_as_plain_numbers():
    t = TemplateMesh(level=1, axes=[1, 0.5, 0.5], scale=1, bottom=0.5)
    assert (t.axes, t.scale, t.bottom) == ((1.0, 0.5, 0.5), 1.0, 0.5)
    assert all(isinstance(a, float) for a in t.axes) and torch.isfinite(t.verts).all()
    assert t.verts[:, 1].min() == pytest.approx(-0.25, abs=1e-3)
