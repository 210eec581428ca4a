"""Named constructors of one kind (timm-style registries): a decorator registers them, ``build`` makes one by name.

The model's compositings, perceptual losses and pose objectives are each one :class:`Registry`;
their modules expose ``register_*``, ``list_*`` and ``build_*`` functions bound to it.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Any, Generic, TypeVar

__all__ = ["Registry"]

F = TypeVar("F", bound=Callable[..., Any])
T = TypeVar("T")


class Registry(Generic[T]):
    """Constructors of one kind by name.

    Args:
        kind: what is registered, in the messages (``"compositing"``).
        key: the config key that names one, in the unknown-name message (default: ``kind``).
    """

    def __init__(self, kind: str, key: str | None = None) -> None:
        self.kind, self.key = kind, key or kind
        self._factories: dict[str, Callable[..., T]] = {}

    def register(self, name: str) -> Callable[[F], F]:
        """Decorator: register a constructor (a class or a function) as ``name``.

        Raises:
            ValueError: ``name`` is already registered.
        """

        def add(factory: F) -> F:
            if name in self._factories:
                raise ValueError(f"{self.kind} {name!r} is already registered")
            self._factories[name] = factory
            return factory

        return add

    def names(self) -> list[str]:
        """The registered names, sorted."""
        return sorted(self._factories)

    def build(self, name: str, **options: Any) -> T:
        """The constructor registered as ``name``, called with the ``options`` its signature names (others are
        ignored, so one config group can feed constructors that each take a part of it).

        Raises:
            ValueError: an unknown name (the known ones listed).
        """
        if name not in self._factories:
            raise ValueError(f"unknown {self.key} {name!r}; known: {self.names()}")
        factory = self._factories[name]
        accepted = inspect.signature(factory).parameters
        return factory(**{k: v for k, v in options.items() if k in accepted})
