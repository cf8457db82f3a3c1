"""Typed node parameters: descriptors, start-up and run-time validation, a core's settings
filled from them, and the warnings for params files and names a node does not declare."""

from __future__ import annotations

import array
import dataclasses
import difflib
import math
import re
from collections.abc import (
    Callable,
    Iterable,
    Mapping,
    Sequence,
)
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Generic, TypeVar

import yaml
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import (
    InvalidParameterTypeException,
    InvalidParameterValueException,
)
from rclpy.node import Node
from rclpy.parameter import Parameter

from vgm_common.diagnostics import Diagnostics
from vgm_common.errors import VgmError
from vgm_common.settings import SettingSpec, settings_specs

if TYPE_CHECKING:
    pass


class ParameterError(VgmError):
    """A parameter has a value of the wrong kind or out of range."""


@dataclass
class Param:
    """One declared parameter: ``default`` fixes its kind (bool, int, float, str, list; a
    list's elements are of the kind of the default's first element, if it has one)."""

    name: str
    default: Any
    description: str
    range: tuple[float, float] | None = None  # (min, max) for numbers, inclusive
    choices: Sequence[str] | None = None
    check: Callable[[Any], str | None] | None = None  # returns a reason if bad
    read_only: bool = False
    kind: type = field(init=False)

    def __post_init__(self) -> None:
        self.kind = type(self.default)

    def _error(self, reason: str, value: Any) -> ParameterError:
        return ParameterError(f'parameter {self.name!r}: {reason}', key=self.name, value=value)

    def coerce(self, value: Any) -> Any:
        """The value in this parameter's kind, or ParameterError with a reason."""
        if self.kind is float and _is_kind(value, int):
            value = float(value)  # `rate:=100` for a float parameter is what users type
        if self.kind is list:
            value = self._coerce_list(value)
        elif not _is_kind(value, self.kind):
            raise self._error(f'expected {self.kind.__name__}, got {value!r}', value)
        if self.kind is float and not math.isfinite(value):
            raise self._error(f'must be finite, got {value}', value)
        if self.range and not self.range[0] <= value <= self.range[1]:
            raise self._error(f'{value} is outside [{self.range[0]}, {self.range[1]}]', value)
        if self.choices and value not in self.choices:
            raise self._error(f'{value!r} is not one of {", ".join(self.choices)}', value)
        reason = self.check(value) if self.check else None
        if reason:
            raise self._error(reason, value)
        return value

    def _coerce_list(self, value: Any) -> list[Any]:
        if isinstance(value, array.array):  # how rclpy hands a numeric array at run time
            value = value.tolist()
        if not isinstance(value, (list, tuple)):
            raise self._error(f'expected a list, got {value!r}', value)
        value = list(value)
        if self.default:
            element = type(self.default[0])
            if element is float:
                value = [float(v) if _is_kind(v, int) else v for v in value]
            if not all(_is_kind(v, element) for v in value):
                raise self._error(f'expected a list of {element.__name__}, got {value!r}', value)
        return value

    def descriptor(self) -> ParameterDescriptor:
        """The ParameterDescriptor to declare it with: the description (plus the choices),
        read-only (except an empty-list default, declared unset) and, for a number, its
        range. Typing is dynamic, so that ``coerce`` reports a wrong kind in one line."""
        text = self.description + (f' One of: {", ".join(self.choices)}.' if self.choices else '')
        # Dynamic typing lets coerce() give the one-line error (and accept an integer
        # for a float) instead of rclpy raising a traceback at declaration.
        # An empty list is declared typed but unset and then set (NodeParameters), which
        # rclpy refuses for a read-only one: its read-only-ness is then ours to enforce.
        descriptor = ParameterDescriptor(
            description=text,
            read_only=self.read_only and self.default != [],
            dynamic_typing=self.default != [],
        )
        if self.range and self.kind is int:
            descriptor.integer_range = [
                IntegerRange(from_value=self.range[0], to_value=self.range[1])
            ]
        elif self.range and self.kind is float:  # `ros2 param describe` shows it
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(self.range[0]), to_value=float(self.range[1]))
            ]
        return descriptor


class NodeParameters:
    """Declares ``params`` on ``node``, validates start-up values (raising
    ParameterError naming the parameter) and later changes (refused with a reason, and
    reported as rejected input to ``diagnostics`` if given). Current values are
    attributes: ``self.params.rate``; ``on_change[name]``, if given, is called with a
    parameter's new value once a change is set. A value given for a name the node does
    not declare is a ParameterError naming the new name if ``renamed`` (old -> new) has
    it, else a warning. Values that must go together (a minimum below its maximum, one
    weight per joint) are checked by ``add_check``."""

    def __init__(
        self,
        node: Node,
        params: Sequence[Param],
        diagnostics: Diagnostics | None = None,
        on_change: Mapping[str, Callable[[Any], None]] | None = None,
        renamed: Mapping[str, str] | None = None,
    ) -> None:
        self._node = node
        self._params = {p.name: p for p in params}
        self._diagnostics = diagnostics
        self._on_change = dict(on_change or {})
        unknown = set(self._on_change) - set(self._params)
        if unknown:  # a programming error: the hook would never run
            raise ValueError(f'on_change names undeclared parameters: {sorted(unknown)}')
        values: dict[str, Any] = {}
        for p in params:
            # rclpy cannot infer an array type from an empty default.
            default = Parameter.Type.STRING_ARRAY if p.default == [] else p.default
            try:
                value = node.declare_parameter(p.name, default, p.descriptor()).value
            except (InvalidParameterTypeException, InvalidParameterValueException) as error:
                # A value of the wrong type, or outside a range the descriptor states.
                raise ParameterError(f'parameter {p.name!r}: {error}', key=p.name) from None
            if value is None and p.default == []:
                # Typed but unset, rclpy's get_parameters service would answer nothing
                # for it (nor for any name asked with it): set the empty list.
                node.set_parameters([Parameter(p.name, Parameter.Type.STRING_ARRAY, [])])
            values[p.name] = _coerce(p, value)
        self._values = values
        self._check_given_names(renamed or {})
        self._checks: list[Callable[[Mapping[str, Any]], str | None]] = []
        node.add_on_set_parameters_callback(self._on_set)
        node.add_post_set_parameters_callback(self._on_changed)

    def _check_given_names(self, renamed: Mapping[str, str]) -> None:
        # rclpy drops a value given for an undeclared name without a word: a typo, or a
        # name from before a rename, would silently leave the default in force. rclpy
        # has no public accessor for what was given.
        if not set(renamed.values()) <= set(self._params):  # a programming error
            raise ValueError(f'renamed to undeclared parameters: {dict(renamed)}')
        given = getattr(self._node, '_parameter_overrides', {})
        unknown = sorted(n for n in given if not self._node.has_parameter(n))
        moved = [old for old in unknown if old in renamed]
        if moved:
            renames = '; '.join(f'{old!r} is now {renamed[old]!r}' for old in moved)
            raise ParameterError(f'renamed parameters (CHANGELOG.md): {renames}', key=moved[0])
        if unknown:
            self._node.get_logger().warning(
                'ignored, not parameters of this node: '
                + ', '.join(_with_suggestion(name, self._params) for name in unknown)
            )

    def __getattr__(self, name: str) -> Any:
        try:
            return self._values[name]
        except KeyError:
            raise AttributeError(name) from None

    @property
    def values(self) -> Mapping[str, Any]:
        """The current values, name -> value (read-only)."""
        return MappingProxyType(self._values)

    @property
    def declared(self) -> Mapping[str, Param]:
        """The declared parameters, name -> Param (read-only)."""
        return MappingProxyType(self._params)

    def add_check(self, check: Callable[[Mapping[str, Any]], str | None]) -> None:
        """``check(values)`` (name -> value) returns a reason if the values do not go
        together. It is run now, raising ParameterError (a start-up error), and on every
        change, which it refuses with the reason."""
        reason = check(self._values)
        if reason:
            raise ParameterError(f'parameters: {reason}')
        self._checks.append(check)

    def _on_set(self, parameters: list[Parameter]) -> SetParametersResult:
        proposed = dict(self._values)
        try:
            for parameter in parameters:
                spec = self._params.get(parameter.name)
                if spec is None:
                    continue
                if spec.read_only:
                    return SetParametersResult(
                        successful=False, reason=f'{spec.name} is read-only'
                    )
                proposed[spec.name] = _coerce(spec, parameter.value)
            reasons = [reason for check in self._checks if (reason := check(proposed))]
            if reasons:
                raise ParameterError(f'parameters: {"; ".join(reasons)}')
        except ParameterError as error:
            if self._diagnostics is not None:
                self._diagnostics.reject('parameter change', error)
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _on_changed(self, parameters: list[Parameter]) -> None:
        # After every set-parameters callback accepted the change: only now is it real.
        for parameter in parameters:
            spec = self._params.get(parameter.name)
            if spec is None:
                continue
            value = self._values[spec.name] = _coerce(spec, parameter.value)
            if spec.name in self._on_change:
                self._on_change[spec.name](value)


def _with_suggestion(name: str, declared: Iterable[str]) -> str:
    """``name``, with the nearest declared name if one is near: 'rat (did you mean rate?)'."""
    near = difflib.get_close_matches(name, list(declared), n=1, cutoff=0.75)
    return f'{name} (did you mean {near[0]}?)' if near else name


def params_file_section_warnings(
    path: str | Path, node_name: str, declared: Callable[[str], bool]
) -> list[str]:
    """What a ``--params-file`` holds for the node of fully qualified name ``node_name``
    that a user would want to hear about, as warning texts: no section applies to it (rcl
    then starts it on its defaults without a word), or the sections that apply (its own,
    ``/**``, ...) hold no name ``declared`` says is its parameter."""
    content = yaml.safe_load(Path(path).read_text())
    if not isinstance(content, dict):
        return []  # check_params_files refused it already
    sections = [str(key) for key in content]
    found = ', '.join(sections) or 'none'
    matching = [key for key in sections if _section_matches(key, node_name)]
    if not matching:
        return [
            f'params file {path} has no section for {node_name} (its sections: {found}): '
            'none of its values apply to this node'
        ]
    names = [
        name
        for key in matching
        for name in _dotted_names((content[key] or {}).get('ros__parameters') or {})
    ]
    if names and not any(declared(name) for name in names):
        return [
            f'params file {path}: its section {", ".join(matching)} holds no parameter '
            f'of {node_name} (its sections: {found})'
        ]
    return []


def _section_matches(section: str, node_name: str) -> bool:
    """Whether the params file section ``section`` applies to ``node_name`` as rcl reads
    it: a name without a namespace is in /, ``/**`` any namespaces, ``*`` one token."""
    key = section if section.startswith('/') else f'/{section}'
    pattern = re.escape(key).replace(r'/\*\*', '(?:/[^/]+)*').replace(r'\*', '[^/]*')
    return re.fullmatch(pattern, node_name) is not None


def _dotted_names(values: Mapping[str, Any], prefix: str = '') -> list[str]:
    """Parameter names of a ``ros__parameters`` mapping: nested mappings are dotted."""
    names = []
    for key, value in values.items():
        if isinstance(value, dict):
            names += _dotted_names(value, f'{prefix}{key}.')
        else:
            names.append(f'{prefix}{key}')
    return names


def params_files_in_args(argv: Sequence[str]) -> list[str]:
    """The files given with ``--params-file`` in a node's arguments."""
    return [path for flag, path in zip(argv, argv[1:]) if flag == '--params-file']


Config = TypeVar('Config')


@dataclass(frozen=True)
class ConfigParams(Generic[Config]):
    """How a core's settings (a dataclass or NamedTuple with a default for every field)
    are filled from a node's parameters: a field takes the parameter of its own name, or
    ``renamed[field]``; a field no parameter names keeps the core's default. The core's
    defaults are the parameters' defaults (``Param('speed', TRACKING.defaults.speed,
    ...)``), and a test checks each node's declared defaults against them."""

    config_type: Callable[..., Config]
    renamed: Mapping[str, str] = field(default_factory=dict)

    @property
    def defaults(self) -> Config:
        """The core's settings with every field at its default."""
        return self.config_type()

    def field_defaults(self) -> dict[str, Any]:
        """Field name -> the core's default, in the fields' order."""
        defaults: Any = self.defaults
        if dataclasses.is_dataclass(defaults):
            return {f.name: getattr(defaults, f.name) for f in dataclasses.fields(defaults)}
        return dict(defaults._asdict())  # a NamedTuple

    def param_names(self, declared: Iterable[str]) -> dict[str, str]:
        """Field -> parameter, for the fields whose parameter is in ``declared``. A
        ``renamed`` entry naming no field or no declared parameter is a programming
        error (the parameter would silently do nothing): ValueError."""
        declared = set(declared)
        fields = self.field_defaults()
        wrong = [
            f'{f} -> {p}' for f, p in self.renamed.items() if f not in fields or p not in declared
        ]
        if wrong:
            raise ValueError(f'{self.config_type.__name__}: no such field or parameter: {wrong}')
        named = {  # a setting's own parameter name (vgm_common.settings.setting)
            f: spec.name
            for f, _, spec in settings_specs(self.config_type)  # type: ignore[arg-type]
            if spec.name
        }
        names = {f: self.renamed.get(f, named.get(f, f)) for f in fields}
        return {f: p for f, p in names.items() if p in declared}

    def declarations(self) -> list[Param]:
        """The parameters of the settings' fields made by ``vgm_common.settings.setting``,
        in the fields' order: the settings dataclass is their one source (name, default,
        description with its unit, range, choices, read-only)."""
        return [
            Param(
                self.renamed.get(f, spec.name or f),
                list(default) if isinstance(default, tuple) else default,
                spec_description(spec),
                range=spec.range,
                choices=spec.choices,
                check=spec.check,
                read_only=spec.read_only,
            )
            for f, default, spec in settings_specs(self.config_type)  # type: ignore[arg-type]
        ]

    def fields(self, params: NodeParameters) -> dict[str, Any]:
        """Field -> the current value of its parameter, for the fields that have one (a
        list where the core's default is a tuple becomes a tuple)."""
        defaults = self.field_defaults()
        return {
            f: tuple(params.values[p]) if isinstance(defaults[f], tuple) else params.values[p]
            for f, p in self.param_names(params.declared).items()
        }

    def build(self, params: NodeParameters) -> Config:
        """The core's settings from the parameters' current values."""
        return self.config_type(**self.fields(params))


def spec_description(spec: SettingSpec) -> str:
    """A setting's description with its unit: 'Square size.' + 'm' -> 'Square size [m].'"""
    if not spec.unit:
        return spec.description
    text = spec.description.rstrip()
    stop = '.' if text.endswith('.') else ''
    return f'{text.removesuffix(".")} [{spec.unit}]{stop}'


def _coerce(spec: Param, value: Any) -> Any:
    # An empty list given on the command line (`topics:=[]`) arrives unset.
    return spec.coerce([] if value is None and spec.kind is list else value)


def _is_kind(value: object, kind: type) -> bool:
    """``isinstance``, except that a bool is no int (ROS keeps them apart)."""
    return isinstance(value, kind) and not (kind is int and isinstance(value, bool))


def check_params_files(argv: Sequence[str]) -> None:
    """Raise VgmError naming the file if a ``--params-file`` in ``argv`` is missing or is
    not a YAML mapping (rcl would fail with a traceback-length message)."""
    for path in params_files_in_args(argv):
        try:
            content = yaml.safe_load(Path(path).read_text())
        except OSError as error:
            raise VgmError(f'cannot read params file {path}: {error.strerror}') from None
        except yaml.YAMLError as error:
            mark = getattr(error, 'problem_mark', None)
            where = f' (line {mark.line + 1})' if mark else ''
            raise VgmError(
                f'params file {path} is not valid YAML{where}: {getattr(error, "problem", error)}'
            ) from None
        if not isinstance(content, dict):
            raise VgmError(
                f'params file {path} must map node names to {{ros__parameters: {{...}}}}'
            )
