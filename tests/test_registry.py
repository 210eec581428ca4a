"""``Registry``: register by name, refuse a second registration, build with the options a constructor names."""

from __future__ import annotations

import pytest

from unicorn.registry import Registry


def test_register_list_and_build_with_the_named_options() -> None:
    things: Registry[tuple] = Registry("thing", key="loss.thing")

    @things.register("pair")
    def pair(a: int, b: int = 2) -> tuple:
        return (a, b)

    assert things.names() == ["pair"]
    assert things.build("pair", a=1, c=3) == (1, 2)  # c is not pair's: ignored
    with pytest.raises(ValueError, match=r"thing 'pair' is already registered"):
        things.register("pair")(pair)
    with pytest.raises(ValueError, match=r"unknown loss.thing 'trio'; known: \['pair'\]"):
        things.build("trio")
