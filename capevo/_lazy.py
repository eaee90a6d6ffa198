"""Lazy re-exports for package ``__init__`` modules.

Packages re-export a curated ``__all__`` without importing every submodule up front:
``capevo.runtime`` would otherwise pull in robosuite and torch just to name a record, and
``capevo.storage`` and ``capevo.registry`` import each other's modules.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_getattr(package: str, homes: Mapping[str, str]) -> Callable[[str], Any]:
    """A module-level ``__getattr__`` that imports ``homes[name]`` on first access to ``name``."""

    def __getattr__(name: str) -> Any:
        try:
            home = homes[name]
        except KeyError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        return getattr(importlib.import_module(home), name)

    return __getattr__
