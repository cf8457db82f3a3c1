"""A core's settings as the one source of its node parameters: each field of a settings
dataclass made with :func:`setting` carries the parameter's name, description, unit,
range, choices and whether it is read-only. The node declares its parameters from the
dataclass (``parameters.ConfigParams.declarations``), fills the dataclass from them, and
``scripts/generate_params.py`` writes the params file and the README table from the same
declarations. No rclpy here: the cores import it."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class SettingSpec:
    """What a setting's parameter says about itself (see :func:`setting`)."""

    description: str
    unit: str = ''  # e.g. 'm', 's', 'px', 'Hz'; '' for a pure number or a word
    range: tuple[float, float] | None = None  # inclusive, for numbers
    choices: tuple[str, ...] | None = None
    check: Callable[[Any], str | None] | None = None  # a reason if the value is bad
    read_only: bool = False
    name: str | None = None  # the parameter's name when it is not the field's


def setting(
    default: Any,
    description: str,
    *,
    unit: str = '',
    range: tuple[float, float] | None = None,  # noqa: A002 (the parameter's word)
    choices: tuple[str, ...] | None = None,
    check: Callable[[Any], str | None] | None = None,
    read_only: bool = False,
    name: str | None = None,
) -> Any:
    """A settings dataclass field that is also a node parameter. ``default`` must be
    immutable (a tuple, not a list: a list parameter's default)."""
    if isinstance(default, (list, dict, set)):
        raise TypeError(f'setting {name or description!r}: a default must be immutable')
    spec = SettingSpec(description, unit, range, choices, check, read_only, name)
    return dataclasses.field(default=default, metadata={'setting': spec})


def settings_specs(settings_type: type) -> Iterator[tuple[str, Any, SettingSpec]]:
    """(field name, default, spec) of the fields of ``settings_type`` made by
    :func:`setting`, in their order (none for a type that is no dataclass)."""
    if not dataclasses.is_dataclass(settings_type):
        return
    for f in dataclasses.fields(settings_type):
        spec = f.metadata.get('setting')
        if spec is not None:
            yield f.name, f.default, spec
