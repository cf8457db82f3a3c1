r"""Message definitions and type hashes of installed ROS 2 interfaces, as rosbag2 stores them.

Plain Python (no rclpy): reads the ``.msg``/``.idl`` files and the ``.json`` type
descriptions that every interface package installs under ``share/<pkg>/msg/``.

``full_definition`` reproduces what Jazzy's rosbag2 writes into an MCAP schema
(``rosbag2_cpp::LocalMessageDefinitionSource::get_full_text``), byte for byte:

- the root type's ``.msg`` file text, verbatim (comments included);
- then, for each dependency in *sorted* order, depth first, each type only once:
  ``"\n" + "=" * 80 + "\n" + "MSG: <pkg>/<Type>\n"`` followed by that type's text.
  The name is spelled as the field type is written in the ``.msg`` file (``std_msgs/Header``,
  and ``<pkg>/<Type>`` for a same-package reference such as ``Point``), not ``pkg/msg/Type``.

Dependencies are found with the same regular expression rosbag2 uses, so the same files
yield the same text. Where a package ships no ``.msg`` for a type, rosbag2 falls back to the
``ros2idl`` encoding (every definition, the root included, behind ``IDL: pkg/msg/Type``);
``definition`` does the same.
"""

from __future__ import annotations

import functools
import importlib.util
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

from vgm_common.errors import VgmError

DELIMITER = '=' * 80 + '\n'
"""The line that separates definitions in both encodings."""

# rosbag2_cpp/src/rosbag2_cpp/message_definitions/local_message_definition_source.cpp (jazzy)
_PACKAGE_TYPENAME_RE = re.compile(r'^([a-zA-Z0-9_]+)/(?:msg/|srv/)?([a-zA-Z0-9_]+)$')
_MSG_FIELD_TYPE_RE = re.compile(r'(?:^|\n)\s*([a-zA-Z0-9_/]+)(?:\[[^\]]*\])?\s+')
_IDL_INCLUDE_RE = re.compile(r'(?:^|\n)#include\s+(?:"|<)([a-zA-Z0-9_/]+)\.idl(?:"|>)')
_PRIMITIVE_TYPES = frozenset(
    (
        'bool',
        'byte',
        'char',
        'float32',
        'float64',
        'int8',
        'uint8',
        'int16',
        'uint16',
        'int32',
        'uint32',
        'int64',
        'uint64',
        'string',
    )
)
# rosbag2's ROSBAG2_CPP_LOCAL_MESSAGE_DEFINITION_SOURCE_MAX_RECURSION_DEPTH
_MAX_RECURSION_DEPTH = 50


class DefinitionNotFoundError(VgmError, LookupError):
    """No installed definition for ``type_name`` (unknown package, type or file)."""

    def __init__(self, type_name: str, detail: str = '') -> None:
        self.type_name = type_name
        super().__init__(
            f'no message definition found for {type_name!r}' + (f': {detail}' if detail else '')
        )


def split_type_name(type_name: str) -> tuple[str, str]:
    """Split ``pkg/msg/Type`` (or ``pkg/Type``) into ``(pkg, Type)``.

    Raises:
        DefinitionNotFoundError: the name is not a ROS interface type name.
    """
    match = _PACKAGE_TYPENAME_RE.match(type_name)
    if match is None:
        raise DefinitionNotFoundError(type_name, 'not a pkg/msg/Type name')
    return match.group(1), match.group(2)


def normalize_type_name(type_name: str) -> str:
    """``sensor_msgs/Image`` or ``sensor_msgs/msg/Image`` -> ``sensor_msgs/msg/Image``."""
    package, name = split_type_name(type_name)
    return f'{package}/msg/{name}'


@functools.lru_cache(maxsize=None)
def package_share_directory(package: str) -> Path:
    """The ``share/<package>`` directory of an installed interface package.

    Looks in the ament index first (what rosbag2 does), then next to the Python prefix
    (``sys.prefix/share``: the pip-installed Jazzy in a venv), then upwards from the
    package's Python module (a colcon install or a relocated venv).

    Raises:
        DefinitionNotFoundError: no share directory with a ``msg`` folder was found.
    """
    candidates = []
    try:
        from ament_index_python.packages import get_package_share_directory

        candidates.append(Path(get_package_share_directory(package)))
    except Exception:  # noqa: BLE001 -- unset AMENT_PREFIX_PATH raises OSError, else not found
        pass
    candidates.append(Path(sys.prefix) / 'share' / package)
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.origin:
        for parent in Path(spec.origin).resolve().parents:
            candidates.append(parent / 'share' / package)
    for candidate in candidates:
        if (candidate / 'msg').is_dir():
            return candidate
    raise DefinitionNotFoundError(package, 'package share directory not found')


def _read_interface_file(package: str, name: str, extension: str) -> str:
    path = package_share_directory(package) / 'msg' / (name + extension)
    try:
        # Bytes, decoded without newline translation: rosbag2 copies the file verbatim.
        return path.read_bytes().decode('utf-8')
    except FileNotFoundError:
        raise DefinitionNotFoundError(f'{package}/msg/{name}', f'{path} does not exist') from None


def _msg_dependencies(text: str, package: str) -> list[str]:
    dependencies: set[str] = set()
    for match in _MSG_FIELD_TYPE_RE.finditer(text):
        field_type = match.group(1)
        if field_type in _PRIMITIVE_TYPES:
            continue
        dependencies.add(field_type if '/' in field_type else f'{package}/{field_type}')
    return sorted(dependencies)  # std::set<std::string> order


def _idl_dependencies(text: str) -> list[str]:
    return sorted({match.group(1) for match in _IDL_INCLUDE_RE.finditer(text)})


def _full_text(
    root: str,
    extension: str,
    dependencies_of: Callable[[str, str], list[str]],
    header: Callable[[str], str],
) -> str:
    """The text of ``root`` and, behind ``header(name)`` each, of its dependencies
    (``dependencies_of(text, package)``), depth first, each once."""
    seen: set[str] = set()

    def append_recursive(type_name: str, depth: int) -> str:
        if depth <= 0:
            raise DefinitionNotFoundError(root, 'maximum recursion depth reached')
        package, name = split_type_name(type_name)
        text = _read_interface_file(package, name, extension)
        result = text
        for dependency in dependencies_of(text, package):
            if dependency not in seen:
                seen.add(dependency)
                result += '\n' + header(dependency) + append_recursive(dependency, depth - 1)
        return result

    return append_recursive(root, _MAX_RECURSION_DEPTH)


@functools.lru_cache(maxsize=None)
def definition(type_name: str) -> tuple[str, str]:
    """``(encoding, text)`` of the complete definition of ``type_name`` as rosbag2 stores it.

    ``encoding`` is ``'ros2msg'`` (the ``.msg`` files exist) or ``'ros2idl'`` (fallback).

    Raises:
        DefinitionNotFoundError: neither ``.msg`` nor ``.idl`` definitions are installed.
    """
    split_type_name(type_name)
    try:
        return 'ros2msg', _full_text(
            type_name, '.msg', _msg_dependencies, lambda dep: f'{DELIMITER}MSG: {dep}\n'
        )
    except DefinitionNotFoundError:
        pass
    root_header = f'{DELIMITER}IDL: {type_name}\n'
    return 'ros2idl', root_header + _full_text(
        type_name,
        '.idl',
        lambda text, _package: _idl_dependencies(text),
        lambda dep: f'{DELIMITER}IDL: {dep}\n',
    )


def full_definition(type_name: str) -> str:
    """The complete ``ros2msg`` definition text of ``type_name`` (e.g. ``sensor_msgs/msg/Image``).

    Raises:
        DefinitionNotFoundError: the type has no installed ``.msg`` definition.
    """
    encoding, text = definition(type_name)
    if encoding != 'ros2msg':
        raise DefinitionNotFoundError(type_name, 'only an IDL definition is installed')
    return text


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """The RIHS01 type description hash of ``type_name`` (``'RIHS01_<64 hex digits>'``).

    Read from the ``share/<pkg>/msg/<Type>.json`` type description that rosidl installs:
    the same string ``ros2 topic info -v`` and rosbag2 report.

    Raises:
        DefinitionNotFoundError: no type description is installed for the type.
    """
    package, name = split_type_name(type_name)
    path = package_share_directory(package) / 'msg' / (name + '.json')
    try:
        description = json.loads(path.read_text(encoding='utf-8'))
    except FileNotFoundError:
        raise DefinitionNotFoundError(type_name, f'{path} does not exist') from None
    wanted = f'{package}/msg/{name}'
    for entry in description.get('type_hashes', []):
        if entry.get('type_name') == wanted:
            return entry['hash_string']
    raise DefinitionNotFoundError(type_name, f'{path} holds no hash for {wanted}')
