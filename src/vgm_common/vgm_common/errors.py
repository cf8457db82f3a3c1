"""The project's exception hierarchy. Nodes catch ``VgmError``, log it once (throttled),
publish a diagnostic and keep serving; exceptions carry the data that explains them."""

from __future__ import annotations

from typing import Any


class VgmError(Exception):
    """Base class of every error the project raises on purpose."""

    def __init__(self, message: str, key: str | None = None, value: Any = None) -> None:
        super().__init__(message)
        self.key = key  # the parameter / scenario key / field at fault, if any
        self.value = value  # the offending value, if useful


class InvalidInput(VgmError, ValueError):
    """A message, array or parameter that cannot be used (wrong shape, NaN, unknown name)."""


class ScenarioError(VgmError, ValueError):
    """A malformed scenario file; ``key`` is the dotted key at fault."""
