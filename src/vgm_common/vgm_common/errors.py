"""The project's exception hierarchy. Nodes catch ``VgmError``, log it once (throttled),
publish a diagnostic and keep serving; exceptions carry the data that explains them.

Under ``VgmError``: ``InvalidInput`` (also a ValueError; the cores' refusals, with ``key``
naming the argument or parameter at fault), ``ScenarioError``, ``ParameterError``,
``TopicTypeError``, ``LaunchError``, calib_node's ``CalibrationError``, bag_tools'
``BagError`` family and ``DefinitionNotFoundError``, and each node's start-up error.
``run_node`` turns any of them at start-up into one line and exit status 2."""

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
