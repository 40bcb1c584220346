"""Typed TOML configuration files: load, validate against frozen dataclasses, write back.

SITL scenarios (``configs/sitl/*/*.toml``) and hardware companion configs
(``configs/hardware/*.toml``) are described by trees of frozen dataclasses. This module turns a
TOML file into such a tree, or raises :class:`ConfigError` naming the file, the dotted key and
the reason, e.g.::

    configs/sitl/chain/three_link.toml: skeleton.n_link: unknown key (did you mean 'n_links'?)

Only the first error found is reported (unknown keys of a table first, then its fields in
declaration order, then the dataclass constructor).

Conventions for dataclass authors
---------------------------------
* Field names are the TOML keys. Fields with ``init=False`` are neither read nor written.
* Supported annotations (``from __future__ import annotations`` is fine; the dataclass and the
  types it names must be resolvable from its module's globals, i.e. defined at module level):

  - ``bool`` (TOML booleans only), ``int`` (TOML integers only, never booleans), ``float``
    (TOML floats or integers, stored as ``float``; nan and inf are rejected), ``str``;
  - ``Literal["a", "b"]`` (str, int or bool choices, matched with their type);
  - ``tuple[X, Y, Z]`` (fixed length), ``tuple[X, ...]`` (any length), nested freely, e.g.
    ``tuple[tuple[int, ...], ...]`` for group layouts ``[[1, 2], [3, 4, 5]]``;
    ``list`` is not supported;
  - ``X | None`` / ``Optional[X]``: TOML has no null, so ``None`` only comes from a default;
  - another dataclass (a TOML table); give it ``default_factory`` to make the table optional;
  - ``dict[str, X]`` (a table of named entries; built into a plain ``dict``).

  Anything else raises ``TypeError`` (a programming error, not a config error).
* A field without ``default``/``default_factory`` is a required key.
* ``__post_init__`` validation raises ``ValueError``. A message about one field must start
  with that field's name, e.g. ``"duration_s must be positive, got -1"``: the error is then
  reported at that key (``scenario.duration_s``). Any other message (cross-field checks:
  start it with a word that is not a field name, e.g. ``"the groups ... do not cover ..."``)
  is reported at the dataclass's own key, or ``(top level)`` for the root dataclass.
* :func:`to_dict` / :func:`dump_toml` omit ``None`` fields, so a field may only be ``None``
  when its default is ``None`` for the written file to load back to an equal instance.
"""

from __future__ import annotations

import dataclasses
import datetime
import difflib
import math
import re
import tomllib
import types
import typing
from collections.abc import Mapping
from os import PathLike
from typing import Any

__all__ = ["ConfigError", "build", "dump_toml", "load_config", "load_toml", "parse_setting", "require_finite_positive",
           "require_nonnegative", "require_positive", "to_dict", "with_settings"]


def require_positive(obj: Any, *names: str) -> None:
    """``ValueError`` naming the first field of ``obj`` in ``names`` that is not > 0 (NaN included)."""
    for name in names:
        value = getattr(obj, name)
        if not value > 0:
            raise ValueError(f"{name} must be positive, got {value}")


def require_finite_positive(obj: Any, *names: str) -> None:
    """``ValueError`` naming the first field of ``obj`` in ``names`` that is not a finite number > 0."""
    for name in names:
        value = getattr(obj, name)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name} must be a finite positive number, got {value!r}")


def require_nonnegative(obj: Any, *names: str) -> None:
    """``ValueError`` naming the first field of ``obj`` in ``names`` that is not >= 0 (NaN included)."""
    for name in names:
        value = getattr(obj, name)
        if not value >= 0:
            raise ValueError(f"{name} must be >= 0, got {value}")

_TOP_LEVEL = "(top level)"
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
_LEADING_NAME = re.compile(r"\s*([A-Za-z_][A-Za-z0-9_]*)")
_REPR_LIMIT = 40
_SCALARS = types.MappingProxyType(
    {
        bool: ("a boolean", "booleans"),
        int: ("an integer", "integers"),
        float: ("a number", "numbers"),
        str: ("a string", "strings"),
    }
)
_STRING_ESCAPES = types.MappingProxyType(
    {'"': '\\"', "\\": "\\\\", "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}
)


class ConfigError(ValueError):
    """A configuration file is unreadable or does not match its dataclass.

    Attributes ``file``, ``key`` (dotted path such as ``companion.groups[1][0]``; ``""`` for
    file-level errors) and ``reason``. ``str(err)`` is ``"<file>: <key>: <reason>"``, or
    ``"<file>: <reason>"`` when ``key`` is empty.
    """

    def __init__(self, file: str, key: str, reason: str):
        super().__init__(str(file), key, reason)
        self.file = str(file)
        self.key = key
        self.reason = reason

    def __str__(self) -> str:
        if self.key:
            return f"{self.file}: {self.key}: {self.reason}"
        return f"{self.file}: {self.reason}"


# ---------------------------------------------------------------------------------------------
# Loading


def load_toml(path: str | PathLike[str]) -> dict[str, Any]:
    """Parse the TOML file at ``path``; raise :class:`ConfigError` if unreadable or invalid."""
    file = str(path)
    try:
        with open(path, "rb") as stream:
            return tomllib.load(stream)
    except FileNotFoundError as exc:
        raise ConfigError(file, "", "no such file") from exc
    except IsADirectoryError as exc:
        raise ConfigError(file, "", "is a directory, not a file") from exc
    except OSError as exc:
        raise ConfigError(file, "", f"cannot read file: {exc.strerror or exc}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(file, "", f"invalid TOML: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(file, "", f"invalid TOML: not UTF-8 text (byte {exc.start}: {exc.reason})") from exc


def parse_setting(text: str) -> tuple[str, Any]:
    """``"firmware.ekf.gate_sigma=4"`` as ``("firmware.ekf.gate_sigma", 4)``: the value is read as a
    TOML value (``4``, ``1e-5``, ``true``, ``[1.0, 0.0, 0.0]``, ``"m8"``), and a bare word that is
    none (``m8``) as a string. ``ValueError`` without ``KEY=VALUE`` or with a malformed key."""
    key, sep, value = text.partition("=")
    key, value = key.strip(), value.strip()
    if not sep or not key or not value:
        raise ValueError(f"{text!r}: expected KEY=VALUE, e.g. firmware.ekf.gate_sigma=4")
    if not all(re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", part) for part in key.split(".")):
        raise ValueError(f"{text!r}: the key is a dotted path of table and key names, e.g. firmware.ekf.gate_sigma")
    try:
        return key, tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        return key, value


def with_settings(data: Mapping[str, Any], settings: Mapping[str, Any], file: str) -> dict[str, Any]:
    """A copy of the parsed TOML ``data`` with each dotted key of ``settings`` set to its value
    (tables on the way are made where absent), to be built and validated like the file itself:
    ``firmware.ekf.gate_sigma`` sets ``gate_sigma`` in ``[firmware.ekf]``. A key whose way passes
    through a value that is not a table is a :class:`ConfigError`."""
    out = _copy_tables(data)
    for dotted, value in settings.items():
        *tables, name = dotted.split(".")
        node = out
        for depth, part in enumerate(tables):
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ConfigError(file, ".".join(tables[:depth + 1]), f"setting {dotted}: not a table")
            node = child
        node[name] = value
    return out


def _copy_tables(data: Mapping[str, Any]) -> dict[str, Any]:
    return {k: _copy_tables(v) if isinstance(v, Mapping) else v for k, v in data.items()}


def load_config(cls: type, path: str | PathLike[str]) -> Any:
    """Load the TOML file at ``path`` and build the dataclass ``cls`` from it."""
    return build(cls, load_toml(path), file=str(path))


def build(cls: type, data: Mapping[str, Any], *, file: str, prefix: str = "", base: Any = None) -> Any:
    """Construct the dataclass ``cls`` from the parsed TOML table ``data``.

    ``file`` and ``prefix`` (the dotted key of ``data`` in the file, ``""`` at the top) only
    serve the error messages. A table given for a field whose type is a dataclass changes only
    the keys it names: the others keep the field's default (``base``: the instance whose values
    the absent keys take, e.g. a ``[firmware.ekf]`` with one key keeps the rest of the tuning the
    firmware's default holds, not the bare class defaults). Raises :class:`ConfigError` for the
    first problem found, and ``TypeError`` if ``cls`` is not a dataclass or uses an unsupported
    annotation.
    """
    if not _is_dataclass_type(cls):
        raise TypeError(f"build() needs a dataclass type, got {cls!r}")
    if not isinstance(data, Mapping):
        raise ConfigError(file, prefix or _TOP_LEVEL, _expected("a table", data))
    fields = _init_fields(cls)
    hints = _type_hints(cls)
    _check_unknown_keys(data, [f.name for f in fields], file, prefix)
    kwargs = {}
    for field in fields:
        annotation = hints[field.name]
        _describe(annotation)  # rejects unsupported annotations even when the key is absent
        key = _join(prefix, field.name)
        if field.name in data:
            if _is_dataclass_type(annotation):
                default = getattr(base, field.name) if base is not None else _field_default(field)
                kwargs[field.name] = build(annotation, data[field.name], file=file, prefix=key,
                                           base=default if isinstance(default, annotation) else None)
            else:
                kwargs[field.name] = _convert(annotation, data[field.name], file, key)
        elif base is not None:
            kwargs[field.name] = getattr(base, field.name)
        elif field.default is dataclasses.MISSING and field.default_factory is dataclasses.MISSING:
            raise ConfigError(file, key, "missing required key")
    return _construct(cls, kwargs, fields, file, prefix)


def _field_default(field: dataclasses.Field) -> Any:
    """The value a field takes when its key is absent (``None`` if it has none)."""
    if field.default_factory is not dataclasses.MISSING:
        return field.default_factory()
    return None if field.default is dataclasses.MISSING else field.default


def _is_dataclass_type(tp: Any) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _init_fields(cls: type) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.init]


def _type_hints(cls: type) -> dict[str, Any]:
    """Resolve the (possibly string) annotations of ``cls``."""
    try:
        return typing.get_type_hints(cls)
    except NameError as exc:
        raise TypeError(
            f"cannot resolve the annotations of {cls.__qualname__} ({exc}); "
            "define the dataclass and the types it uses at module level"
        ) from exc


def _check_unknown_keys(data: Mapping[str, Any], names: list[str], file: str, prefix: str) -> None:
    for name in data:
        if name not in names:
            raise ConfigError(file, _join(prefix, str(name)), _unknown_reason(str(name), names))


def _unknown_reason(name: str, names: list[str]) -> str:
    close = difflib.get_close_matches(name, names, n=1)
    if close:
        return f"unknown key (did you mean '{close[0]}'?)"
    if names:
        return f"unknown key (expected one of: {', '.join(names)})"
    return "unknown key (this table takes no keys)"


def _construct(cls: type, kwargs: dict[str, Any], fields: list[dataclasses.Field], file: str, prefix: str) -> Any:
    """Call the constructor, mapping a ``ValueError`` from ``__post_init__`` to a key."""
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except ValueError as exc:
        message = str(exc)
        raise ConfigError(file, _post_init_key(message, fields, prefix), message) from exc


def _post_init_key(message: str, fields: list[dataclasses.Field], prefix: str) -> str:
    """The field the message starts with (joined to ``prefix``), else the table's own key."""
    match = _LEADING_NAME.match(message)
    if match and match.group(1) in {f.name for f in fields}:
        return _join(prefix, match.group(1))
    return prefix or _TOP_LEVEL


def _join(prefix: str, name: str) -> str:
    """Dotted key path ``prefix.name``, quoting ``name`` as TOML does when it is not bare."""
    segment = name if _BARE_KEY.fullmatch(name) else _toml_string(name)
    return f"{prefix}.{segment}" if prefix else segment


# ---------------------------------------------------------------------------------------------
# Type descriptions and conversion


def _describe(tp: Any) -> tuple[str, str]:
    """(singular, plural) description of annotation ``tp``; ``TypeError`` if unsupported."""
    if tp in _SCALARS:
        return _SCALARS[tp]
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is typing.Literal:
        if not all(isinstance(choice, (str, int)) for choice in args):
            raise TypeError(f"unsupported Literal {tp!r}: choices must be str, int or bool")
        return f"one of {_choices(args)}", "values"
    if origin in (typing.Union, types.UnionType):
        return _describe(_optional_arg(tp))
    if origin is tuple:
        return _describe_tuple(args)
    if origin is dict:
        if args[0] is not str:
            raise TypeError(f"unsupported annotation {tp!r}: TOML table keys are strings, use dict[str, X]")
        _describe(args[1])
        return "a table", "tables"
    if _is_dataclass_type(tp):
        return "a table", "tables"
    raise TypeError(
        f"unsupported field annotation {tp!r}: use bool, int, float, str, Literal[...], "
        "tuple[...], dict[str, X], X | None or a dataclass"
    )


def _describe_tuple(args: tuple[Any, ...]) -> tuple[str, str]:
    if _is_variadic(args):
        plural = _describe(args[0])[1]
        return f"an array of {plural}", f"arrays of {plural}"
    count = _count_phrase(args)
    return f"an array of {count}", f"arrays of {count}"


def _is_variadic(args: tuple[Any, ...]) -> bool:
    return len(args) == 2 and args[1] is Ellipsis


def _count_phrase(args: tuple[Any, ...]) -> str:
    """``"3 numbers"`` for a homogeneous fixed tuple, else ``"<n> elements"``."""
    plurals = {_describe(arg)[1] for arg in args}
    if len(args) > 1 and len(plurals) == 1:
        return f"{len(args)} {plurals.pop()}"
    return "1 element" if len(args) == 1 else f"{len(args)} elements"


def _optional_arg(tp: Any) -> Any:
    """``X`` of ``X | None``; other unions are not supported."""
    args = typing.get_args(tp)
    others = [arg for arg in args if arg is not type(None)]
    if len(args) != 2 or len(others) != 1:
        raise TypeError(f"unsupported union {tp!r}: only X | None (Optional[X]) is supported")
    return others[0]


def _convert(tp: Any, value: Any, file: str, key: str) -> Any:
    """Check ``value`` (parsed TOML) against annotation ``tp`` and convert it."""
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        return _convert_literal(tp, value, file, key)
    if origin in (typing.Union, types.UnionType):
        return _convert(_optional_arg(tp), value, file, key)
    if origin is tuple:
        return _convert_tuple(tp, value, file, key)
    if origin is dict:
        return _convert_dict(tp, value, file, key)
    if _is_dataclass_type(tp):
        if not isinstance(value, Mapping):
            raise ConfigError(file, key, _expected("a table", value))
        return build(tp, value, file=file, prefix=key)
    return _convert_scalar(tp, value, file, key)


def _convert_scalar(tp: type, value: Any, file: str, key: str) -> Any:
    is_number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is float and is_number:
        return _finite_float(value, file, key)
    if tp is int and is_number and isinstance(value, int):
        return value
    if tp in (bool, str) and isinstance(value, tp):
        return value
    raise ConfigError(file, key, _expected(_describe(tp)[0], value))


def _finite_float(value: int | float, file: str, key: str) -> float:
    try:
        number = float(value)
    except OverflowError:
        number = math.inf
    if not math.isfinite(number):
        raise ConfigError(file, key, "must be a finite number")
    return number


def _convert_literal(tp: Any, value: Any, file: str, key: str) -> Any:
    choices = typing.get_args(tp)
    if any(type(value) is type(choice) and value == choice for choice in choices):
        return value
    raise ConfigError(file, key, f"must be one of {_choices(choices)} (got {_show(value)})")


def _convert_tuple(tp: Any, value: Any, file: str, key: str) -> tuple[Any, ...]:
    args = typing.get_args(tp)
    if not isinstance(value, list):
        raise ConfigError(file, key, _expected(_describe(tp)[0], value))
    if _is_variadic(args):
        element_types = (args[0],) * len(value)
    elif len(value) != len(args):
        raise ConfigError(file, key, f"expected {_count_phrase(args)}, got {len(value)}")
    else:
        element_types = args
    return tuple(
        _convert(element_type, element, file, f"{key}[{index}]")
        for index, (element_type, element) in enumerate(zip(element_types, value))
    )


def _convert_dict(tp: Any, value: Any, file: str, key: str) -> dict[str, Any]:
    value_type = typing.get_args(tp)[1]
    if not isinstance(value, Mapping):
        raise ConfigError(file, key, _expected("a table", value))
    return {name: _convert(value_type, item, file, _join(key, name)) for name, item in value.items()}


def _choices(choices: tuple[Any, ...]) -> str:
    return ", ".join(_show(choice) for choice in choices)


def _expected(description: str, value: Any) -> str:
    return f"expected {description}, got {_toml_type(value)} {_show(value)}"


def _show(value: Any) -> str:
    """Short representation of a parsed TOML value (booleans as TOML writes them)."""
    text = ("true" if value else "false") if isinstance(value, bool) else repr(value)
    return text if len(text) <= _REPR_LIMIT else text[: _REPR_LIMIT - 3] + "..."


def _toml_type(value: Any) -> str:
    """TOML name of the type of a parsed value."""
    for python_type, name in (
        (bool, "boolean"),
        (int, "integer"),
        (float, "float"),
        (str, "string"),
        (list, "array"),
        (Mapping, "table"),
        (datetime.datetime, "datetime"),
        (datetime.date, "date"),
        (datetime.time, "time"),
    ):
        if isinstance(value, python_type):
            return name
    return type(value).__name__


# ---------------------------------------------------------------------------------------------
# Writing


def to_dict(obj: Any) -> dict[str, Any]:
    """Plain-data form of dataclass ``obj`` (inverse of :func:`build`).

    Nested dataclasses become dicts, tuples become lists, ``None`` fields are omitted and
    ``init=False`` fields are skipped.
    """
    if not dataclasses.is_dataclass(obj) or isinstance(obj, type):
        raise TypeError(f"to_dict() needs a dataclass instance, got {obj!r}")
    result = {}
    for field in _init_fields(type(obj)):
        value = getattr(obj, field.name)
        if value is not None:
            result[field.name] = _plain(value)
    return result


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return to_dict(value)
    if isinstance(value, (tuple, list)):
        return [_plain(item) for item in value]
    if isinstance(value, Mapping):
        return {name: _plain(item) for name, item in value.items() if item is not None}
    return value


def dump_toml(obj: Any) -> str:
    """TOML document of ``to_dict(obj)`` (``obj`` may also be a plain mapping).

    ``build(type(obj), tomllib.loads(dump_toml(obj)), file=...) == obj`` for any dataclass
    :func:`build` can produce. Scalars and arrays come first in each table, then sub-tables
    as ``[a.b]`` sections; tables inside arrays are written inline.
    """
    lines: list[str] = []
    _emit_table(_plain(obj), (), lines)
    return "\n".join(lines) + "\n" if lines else ""


def _emit_table(table: Mapping[str, Any], path: tuple[str, ...], lines: list[str]) -> None:
    """Append ``table`` as a ``[path]`` section (keys first, then its sub-tables)."""
    subtables = [(name, value) for name, value in table.items() if isinstance(value, Mapping)]
    keys = [(name, value) for name, value in table.items() if not isinstance(value, Mapping)]
    if path and (keys or not subtables):  # a table holding only tables needs no header
        if lines:
            lines.append("")
        lines.append(f"[{'.'.join(_toml_key(name) for name in path)}]")
    lines.extend(f"{_toml_key(name)} = {_toml_value(value)}" for name, value in keys)
    for name, value in subtables:
        _emit_table(value, (*path, name), lines)


def _toml_key(name: str) -> str:
    return name if _BARE_KEY.fullmatch(name) else _toml_string(name)


def _toml_value(value: Any) -> str:
    """Inline TOML for a scalar, array or (inline) table."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return int.__repr__(value)
    if isinstance(value, float):
        return _toml_float(value)
    if isinstance(value, str):
        return _toml_string(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    if isinstance(value, Mapping):
        items = ", ".join(f"{_toml_key(name)} = {_toml_value(item)}" for name, item in value.items())
        return "{ " + items + " }" if items else "{}"
    raise TypeError(f"cannot write {type(value).__name__} value {value!r} as TOML")


def _toml_float(value: float) -> str:
    """Shortest round-tripping form; Python's float repr always has a '.' or an exponent."""
    if math.isnan(value):
        return "nan"
    if math.isinf(value):
        return "inf" if value > 0 else "-inf"
    return float.__repr__(value)


def _toml_string(text: str) -> str:
    """TOML basic string (double quotes, escapes for quotes, backslashes and controls)."""
    return '"' + "".join(_escape_char(char) for char in text) + '"'


def _escape_char(char: str) -> str:
    if char in _STRING_ESCAPES:
        return _STRING_ESCAPES[char]
    code = ord(char)
    if code < 0x20 or code == 0x7F:
        return f"\\u{code:04X}"
    if 0xD800 <= code <= 0xDFFF:
        raise ValueError(f"cannot write the lone surrogate U+{code:04X} as TOML")
    return char
