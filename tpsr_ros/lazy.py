"""Names of a package imported on first use (PEP 562), so importing the package is cheap.

``tpsr_ros``, ``tpsr_ros.filter_node`` and ``tpsr_ros.view`` list their public names with
the module each comes from; :func:`lazy_exports` gives the package's ``__getattr__`` and
``__dir__``, which import a name's module when the name is first read and keep the value.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

__all__ = ["lazy_exports"]


def lazy_exports(
    package: str, api: Mapping[str, str], public: Sequence[str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` of ``package``: ``api`` maps each name to its module."""

    def __getattr__(name: str) -> Any:
        module = api.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted([*vars(sys.modules[package]), *public])

    return __getattr__, __dir__
