"""Named things of one family, timm-style: a decorator (or :meth:`Registry.add`) registers them by name, and
:meth:`Registry.get` / :meth:`Registry.build` look them up.

Every named family of the library is one :class:`Registry`: the renderer backends (:mod:`unicorn.render`, with the
``unicorn.renderers`` entry points), the datasets (:mod:`unicorn.data.registry`), the evaluation protocols
(:mod:`unicorn.evaluation.protocols`), the compositings (:mod:`unicorn.model.compositing`), the perceptual losses,
the pose objectives and the viewpoint supervisions. Their modules expose ``register_*``, ``list_*`` and ``build_*``
functions bound to it. An unknown name is one error everywhere, :class:`UnknownNameError`, whose message lists the
known names; an option that a constructor does not take is :class:`UnknownOptionError`, whose message names it and
lists the options taken.

Plugins: your own entries are registered by importing the module that registers them; in Python, import it. The
command-line tools import, before they read their settings (:func:`load_plugins`), the modules named in the
environment variable :data:`PLUGINS_ENV` (``UNICORN_PLUGINS=mypkg.unicorn_parts,other_module``: importable, e.g. on
``PYTHONPATH``) and, from installed packages, the entry points of the group :data:`PLUGIN_GROUP`
(``[project.entry-points."unicorn.plugins"]``, ``any_name = "mypkg.unicorn_parts"``).
"""

from __future__ import annotations

import importlib
import inspect
import os
import warnings
from collections.abc import Callable, Collection, Iterable, Iterator, Mapping
from importlib.metadata import entry_points
from typing import Any, Generic, TypeVar

from unicorn.errors import UserError

__all__ = [
    "PLUGINS_ENV",
    "PLUGIN_GROUP",
    "IncompleteEntryError",
    "PluginError",
    "Registry",
    "UnknownNameError",
    "UnknownOptionError",
    "check_options",
    "keyword_options",
    "load_plugins",
]

#: the environment variable naming the modules to import before the first lookup (comma-separated)
PLUGINS_ENV = "UNICORN_PLUGINS"
#: the entry-point group of installed packages' plugin modules (each entry's value: a module name)
PLUGIN_GROUP = "unicorn.plugins"
_plugins_loaded = False

T = TypeVar("T")
F = TypeVar("F")


class UnknownNameError(UserError, ValueError):
    """A name that no entry of a registry has (the message lists the known ones)."""


class UnknownOptionError(UserError, TypeError):
    """An option that the named constructor does not take (the message names it and lists the ones it takes); a
    ``TypeError``, as Python's own unexpected keyword argument."""


class IncompleteEntryError(UserError, TypeError):
    """An entry that lacks a method its family needs (the message names it)."""


class PluginError(UserError, ImportError):
    """A module named in :data:`PLUGINS_ENV` that cannot be imported (the message names it and why)."""


def load_plugins() -> None:
    """Import the plugin modules once (see the module docstring): :data:`PLUGINS_ENV`'s first, then the
    :data:`PLUGIN_GROUP` entry points. A broken entry point warns and is skipped, as a broken renderer entry point;
    a module you named yourself is an error.

    Raises:
        PluginError: a module of :data:`PLUGINS_ENV` fails to import.
    """
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True  # first: a plugin that looks something up while it is imported must not come back here
    for name in (part.strip() for part in os.environ.get(PLUGINS_ENV, "").split(",")):
        if not name:
            continue
        try:
            importlib.import_module(name)
        except Exception as err:
            raise PluginError(f"{PLUGINS_ENV}: cannot import {name!r}: {type(err).__name__}: {err}") from err
    for ep in entry_points(group=PLUGIN_GROUP):
        try:
            importlib.import_module(ep.value)
        except Exception as err:  # a broken plugin must not break the built-in entries
            warnings.warn(
                f"could not load the {PLUGIN_GROUP} entry point {ep.name!r} ({ep.value}): {err}", stacklevel=3
            )


def keyword_options(factory: Callable[..., Any]) -> list[str] | None:
    """The names ``factory`` takes as keyword arguments, in order; None when it takes any (``**kwargs``)."""
    params = inspect.signature(factory).parameters.values()
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params):
        return None
    return [p.name for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]


def check_options(what: str, options: Iterable[str], accepted: Collection[str]) -> None:
    """Refuse the first of ``options`` that is not ``accepted``.

    Args:
        what: the thing that takes the options, in the message (``"renderer 'layered'"``).

    Raises:
        UnknownOptionError: an option not in ``accepted`` (named; the accepted ones listed).
    """
    unknown = [key for key in options if key not in accepted]
    if unknown:
        raise UnknownOptionError(f"{what} takes no option {unknown[0]!r}; its options: {sorted(accepted)}")


class Registry(Generic[T]):
    """Entries of one family by name: constructors (called by :meth:`build`) or plain values (read by :meth:`get`).

    Args:
        kind: what is registered, in the messages (``"compositing"``).
        key: the setting that names one, in the unknown-name message (default: ``kind``).
        base: a class every entry must subclass (``nn.Module`` for renderers), or None.
        entry_points: an entry-point group whose entries (``name = "package.module:Object"``) are registered on the
            first lookup, or None. A broken entry point warns and is skipped.
        methods: the methods every entry's objects must have (a class entry is checked when it is registered, what
            another constructor returns when it is built).
    """

    def __init__(
        self,
        kind: str,
        key: str | None = None,
        *,
        base: type | None = None,
        entry_points: str | None = None,
        methods: tuple[str, ...] = (),
    ) -> None:
        self.kind, self.key, self.base, self.methods = kind, key or kind, base, methods
        self._entries: dict[str, T] = {}
        self._entry_point_group = entry_points

    def add(self, name: str, entry: F, *, overwrite: bool = False) -> F:
        """Register ``entry`` as ``name`` and return it. Registering the same entry again changes nothing.

        Raises:
            ValueError: an empty name, or ``name`` registered to another entry (unless ``overwrite``, which warns).
            TypeError: an entry that is not a subclass of ``base``.
        """
        if not isinstance(name, str) or not name:
            raise ValueError(f"a {self.kind} name must be a non-empty string, got {name!r}")
        if self.base is not None and not (isinstance(entry, type) and issubclass(entry, self.base)):
            raise TypeError(f"a {self.kind} must be a subclass of {self.base.__name__}, got {entry!r}")
        if isinstance(entry, type):
            self._check_methods(name, entry)
        old = self._entries.get(name)
        if old is not None and old is not entry:
            if not overwrite:
                raise ValueError(
                    f"{self.kind} {name!r} is already registered ({_describe(old)}); pass overwrite=True to replace it"
                )
            warnings.warn(f"replacing {self.kind} {name!r}", stacklevel=3)
        self._entries[name] = entry  # type: ignore[assignment]
        return entry

    def register(self, name: str, *, overwrite: bool = False) -> Callable[[F], F]:
        """Decorator: register a constructor (a class or a function) as ``name`` (see :meth:`add`)."""
        return lambda entry: self.add(name, entry, overwrite=overwrite)

    def remove(self, name: str) -> None:
        """Forget ``name`` (nothing happens when it is not registered)."""
        self._entries.pop(name, None)

    def names(self) -> list[str]:
        """The registered names, sorted."""
        return sorted(self._loaded())

    def __iter__(self) -> Iterator[str]:
        """The registered names, in the order they were registered."""
        return iter(list(self._loaded()))

    def __len__(self) -> int:
        return len(self._loaded())

    def __contains__(self, name: object) -> bool:
        return name in self._loaded()

    def items(self) -> list[tuple[str, T]]:
        """``(name, entry)`` pairs, in the order they were registered."""
        return list(self._loaded().items())

    def get(self, name: str) -> T:
        """The entry registered as ``name``.

        Raises:
            UnknownNameError: an unknown name (the known ones listed).
        """
        entries = self._loaded()
        if name not in entries:
            raise UnknownNameError(f"unknown {self.key} {name!r}; known: {self.names()}")
        return entries[name]

    def build(self, name: str, options: Mapping[str, Any] | None = None, *, group_keys: Collection[str] = ()) -> Any:
        """Call the constructor registered as ``name`` with ``options``.

        Args:
            name: a registered name.
            options: keyword arguments of the constructor.
            group_keys: the keys of the configuration group that ``options`` is, when one group feeds several
                constructors that each take a part (the ``loss`` group): those the constructor does not take are
                left out. Any other option it does not take is refused.

        Raises:
            UnknownNameError: an unknown name (the known ones listed).
            UnknownOptionError: an option that is neither the constructor's nor one of ``group_keys``.
            IncompleteEntryError: what the constructor returned lacks one of :attr:`methods`.
        """
        factory: Callable[..., Any] = self.get(name)  # type: ignore[assignment]
        options = dict(options or {})
        accepted = keyword_options(factory)
        if accepted is not None:  # else it takes any keyword: it checks its own options
            check_options(f"{self.kind} {name!r}", (k for k in options if k not in group_keys), accepted)
            options = {k: v for k, v in options.items() if k in accepted}
        built = factory(**options)
        self._check_methods(name, built)
        return built

    def _check_methods(self, name: str, entry: Any) -> None:
        """Refuse an entry (a class, or what a constructor built) without one of :attr:`methods`."""
        missing = [m for m in self.methods if not callable(getattr(entry, m, None))]
        if missing:
            raise IncompleteEntryError(
                f"{self.kind} {name!r} ({_describe(entry)}) has no {' and no '.join(missing)}; a {self.kind} needs "
                f"{', '.join(self.methods)}"
            )

    def _loaded(self) -> dict[str, T]:
        """The entries, after registering the entry points' on first use."""
        if self._entry_point_group is not None:
            group, self._entry_point_group = self._entry_point_group, None
            for ep in entry_points(group=group):
                try:
                    entry = ep.load()
                    old = self._entries.get(ep.name)
                    if old is not None and old is not entry:  # a built-in's name, or another plugin's
                        warnings.warn(
                            f"the {group} entry point {ep.name!r} ({ep.value}) is not used: {self.kind} {ep.name!r} "
                            f"is already registered ({_describe(old)}); give the entry point another name",
                            stacklevel=3,
                        )
                        continue
                    self.add(ep.name, entry)
                except Exception as err:  # a broken plugin must not break the built-in entries
                    message = f"could not load {self.kind} entry point {ep.name!r} ({ep.value}): {err}"
                    warnings.warn(message, stacklevel=3)
        return self._entries


def _describe(entry: object) -> str:
    """An entry in a message: its qualified name, else its type's (not a whole dataclass's repr)."""
    return getattr(entry, "__qualname__", None) or type(entry).__qualname__
