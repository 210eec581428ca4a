"""A griffe extension for the API pages, so that the docstrings read well as Markdown:

- ``Example:`` sections are read as Google-style ``Examples:`` sections (their doctest lines render as code);
- Sphinx roles (``:class:`unicorn.model.Unicorn```, ``:func:`~unicorn.metrics.chamfer_l1```) render as inline
  code, the ``~`` form with its last component only.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

_EXAMPLE = re.compile(r"^(\s*)Example:[ \t]*$", flags=re.MULTILINE)
_ROLE = re.compile(r":(?:class|func|meth|mod|data|attr|exc|obj):`(~?)([^`]+)`")


def _role(match: re.Match[str]) -> str:
    target = match.group(2)
    return f"`{target.rsplit('.', 1)[-1] if match.group(1) else target}`"


class MarkdownDocstrings(griffe.Extension):
    def on_object(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(_role, _EXAMPLE.sub(r"\1Examples:", obj.docstring.value))
