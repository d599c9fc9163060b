"""One strict loader from plain YAML/JSON data to typed config dataclasses, used by every stage and the pipeline.

`load(cls, data, source)` builds `cls` (nested dataclasses, tuples, lists, dicts, Optional and other unions,
Literal, Enum, Path, int/float/bool/str) and rejects, with one `ConfigError` line naming the file and the dotted
key, what a typo or a wrong value would otherwise let through silently:

- unknown keys, with the closest known key suggested: `stage.yaml: unknown key 'sphere_radus' (did you mean
  'sphere_radius'?)`;
- wrong types, with the expected type: `p.yaml: train.optim.lr: expected a number, got 'fast'`. No silent
  conversions: an int is accepted for a float, a bool never for a number, a string never for a number;
- a dataclass's own value checks: a `__post_init__` that raises `ConfigError` (see `require`, `require_choice`)
  or `ValueError` gives `p.yaml: train.optim.lr: must be > 0, got -1`.

`ConfigError` keeps the key path and the file apart from the message, so a stage's error can be placed inside a
larger file (`err.within(source, prefix)`): the pipeline config reports `train.optim.lr`, the stage's own file
`optim.lr`.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import os
import re
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from functools import cache
from pathlib import Path, PurePath
from typing import Any, Literal, TypeVar, Union

import yaml

from lightstage.errors import LightstageError

T = TypeVar("T")
PathPart = str | int
_NONE = type(None)


def dotted(path: Sequence[PathPart]) -> str:
    """('train', 'optim', 'lr') -> 'train.optim.lr'; list indices as [i]: ('cameras', 0, 'id') -> 'cameras[0].id'."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def _as_path(path: Sequence[PathPart] | str | None) -> tuple[PathPart, ...]:
    if path is None or path == "":
        return ()
    if isinstance(path, str):
        return tuple(path.split("."))
    return tuple(path)


class ConfigError(LightstageError, ValueError):
    """A bad config value: `source: key.path: problem` (source and path are optional and can be added later)."""

    def __init__(
        self, problem: str, path: Sequence[PathPart] | str | None = (), source: str | None = None
    ) -> None:
        self.problem = problem
        self.path = _as_path(path)
        self.source = source
        super().__init__(problem)

    def _body(self) -> str:
        key = dotted(self.path)
        return f"{key}: {self.problem}" if key else self.problem

    def __str__(self) -> str:
        return f"{self.source}: {self._body()}" if self.source else self._body()

    def __reduce__(self) -> Any:  # pickles (dask) with its fields, not only the message
        return (_rebuild, (type(self), self.__dict__))

    def within(self, source: str | None = None, prefix: Sequence[PathPart] | str | None = ()) -> ConfigError:
        """This error placed inside a larger document: `prefix` before its path and `source` as its file.
        An error that already names its own file (a base config the section points at) is kept as it is."""
        if self.source:
            return self
        err = type(self).__new__(type(self))
        err.__dict__.update(self.__dict__)
        err.path = _as_path(prefix) + self.path
        err.source = source
        Exception.__init__(err, err.problem)
        return err


class UnknownKeyError(ConfigError):
    """A key the config class does not have: names the dotted key and the closest known one."""

    def __init__(
        self, path: Sequence[PathPart] | str, known: Iterable[str], source: str | None = None
    ) -> None:
        self.known = tuple(known)
        super().__init__("unknown key", path, source)

    def _body(self) -> str:
        key = str(self.path[-1]) if self.path else ""
        close = suggest(key, self.known)
        if close is not None:
            hint = f"did you mean '{dotted((*self.path[:-1], close))}'?"
        elif self.known:
            hint = f"known: {', '.join(self.known)}"
        else:
            hint = "no keys are allowed here"
        return f"unknown key '{dotted(self.path)}' ({hint})"


def _rebuild(cls: type, state: dict[str, Any]) -> ConfigError:
    err = cls.__new__(cls)
    err.__dict__.update(state)
    Exception.__init__(err, err.problem)
    return err


def suggest(name: str, known: Iterable[str]) -> str | None:
    """The known name closest to `name` (difflib, ignoring case), or None when nothing is close."""
    by_lower = {str(k).lower(): str(k) for k in known}
    close = difflib.get_close_matches(str(name).lower(), list(by_lower), n=1, cutoff=0.6)
    return by_lower[close[0]] if close else None


def check_keys(
    data: Mapping[Any, Any],
    known: Iterable[str],
    path: Sequence[PathPart] | str | None = (),
    source: str | None = None,
) -> None:
    """Raise UnknownKeyError for the first key of `data` (file order) that is not in `known`."""
    known = tuple(known)
    for key in data:
        if key not in known:
            raise UnknownKeyError((*_as_path(path), str(key)), known, source)


def require(ok: bool, key: str, problem: str) -> None:
    """For `__post_init__` value checks: raise ConfigError(problem) at `key` unless `ok`."""
    if not ok:
        raise ConfigError(problem, key)


def require_choice(value: Any, key: str, choices: Sequence[Any]) -> None:
    """For `__post_init__`: `value` must be one of `choices` (the error suggests the closest one)."""
    if value not in choices:
        raise ConfigError(_choice_problem(value, choices), key)


def _choice_problem(value: Any, choices: Sequence[Any]) -> str:
    problem = f"expected one of {', '.join(repr(c) for c in choices)}, got {value!r}"
    close = suggest(value, [str(c) for c in choices]) if isinstance(value, str) else None
    return problem + (f" (did you mean '{close}'?)" if close else "")


# ---- conversion ----------------------------------------------------------------------------------


def load(
    cls: type[T],
    data: Any,
    source: str | None = None,
    path: Sequence[PathPart] | str | None = (),
    *,
    ignore: Iterable[str] = (),
) -> T:
    """Build `cls` (usually a dataclass) from plain data; every problem is a ConfigError naming `source` and
    the dotted key. None stands for an empty mapping. Keys in `ignore` are dropped at the top level (derived
    keys a writer adds, such as a description)."""
    if ignore and isinstance(data, Mapping):
        drop = set(ignore)
        data = {k: v for k, v in data.items() if k not in drop}
    try:
        return convert(cls, data, _as_path(path))
    except ConfigError as e:
        raise e.within(source) from None


def convert(tp: Any, value: Any, path: tuple[PathPart, ...] = ()) -> Any:
    """`value` as type `tp` (an annotation), or ConfigError at `path` (no source)."""
    if tp is Any or tp is object:
        return value
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return _dataclass(tp, value, path)
    origin = typing.get_origin(tp)
    if origin is Union or isinstance(tp, types.UnionType):
        return _union(tp, value, path)
    if origin is Literal:
        choices = typing.get_args(tp)
        if not any(value == c and type(value) is type(c) for c in choices):
            raise ConfigError(_choice_problem(value, choices), path)
        return value
    if tp is _NONE:
        if value is not None:
            raise ConfigError(f"expected null, got {_show(value)}", path)
        return None
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return _enum(tp, value, path)
    if tp in _SCALARS:
        return _SCALARS[tp](value, path)
    if isinstance(tp, type) and issubclass(tp, PurePath):
        if isinstance(value, str | os.PathLike) and not isinstance(value, bool):
            return tp(value)
        raise _wrong(tp, value, path)
    if origin in (list, tuple, set, frozenset) or tp in (list, tuple, set, frozenset) or origin is Sequence:
        return _sequence(tp, value, path)
    if origin in (dict, Mapping) or tp in (dict, Mapping):
        return _mapping(tp, value, path)
    raise TypeError(f"lightstage.config: unsupported annotation {tp!r} at {dotted(path) or '<top>'}")


def _bool(value: Any, path: tuple[PathPart, ...]) -> bool:
    if isinstance(value, bool):
        return value
    raise _wrong(bool, value, path)


def _int(value: Any, path: tuple[PathPart, ...]) -> int:
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    raise _wrong(int, value, path)


def _float(value: Any, path: tuple[PathPart, ...]) -> float:
    if isinstance(value, int | float) and not isinstance(value, bool):
        return float(value)
    raise _wrong(float, value, path)


def _str(value: Any, path: tuple[PathPart, ...]) -> str:
    if isinstance(value, str):
        return value
    raise _wrong(str, value, path)


_SCALARS: dict[Any, Any] = {bool: _bool, int: _int, float: _float, str: _str}


def _dataclass(cls: type, value: Any, path: tuple[PathPart, ...]) -> Any:
    if value is None:
        value = {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"expected a mapping, got {_show(value)}", path)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    check_keys(value, fields, path)
    hints = _hints(cls)
    for name, f in fields.items():
        if (
            name not in value
            and f.default is dataclasses.MISSING
            and f.default_factory is dataclasses.MISSING
        ):
            raise ConfigError("missing (required)", (*path, name))
    kwargs = {k: convert(hints[k], v, (*path, k)) for k, v in value.items()}
    try:
        return cls(**kwargs)
    except ConfigError as e:
        raise e.within(None, path) from None
    except ValueError as e:  # a __post_init__ value check
        raise ConfigError(str(e), path) from None


@cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _union(tp: Any, value: Any, path: tuple[PathPart, ...]) -> Any:
    options = [a for a in typing.get_args(tp) if a is not _NONE]
    if value is None:
        if len(options) < len(typing.get_args(tp)):
            return None
        raise ConfigError(f"must not be empty (expected {describe(tp)})", path)
    errors: list[tuple[Any, ConfigError]] = []
    for option in options:
        try:
            return convert(option, value, path)
        except ConfigError as e:
            errors.append((option, e))
    for option, e in errors:  # a mapping that fails inside its dataclass: that error is the useful one
        if isinstance(value, Mapping) and dataclasses.is_dataclass(option):
            raise e
    raise _wrong(tp, value, path)


def _enum(tp: type[enum.Enum], value: Any, path: tuple[PathPart, ...]) -> Any:
    for member in tp:
        if member.value == value and type(member.value) is type(value):
            return member
    raise ConfigError(_choice_problem(value, [m.value for m in tp]), path)


def _sequence(tp: Any, value: Any, path: tuple[PathPart, ...]) -> Any:
    if not isinstance(value, list | tuple):
        raise _wrong(tp, value, path)
    origin = typing.get_origin(tp) or tp
    args = typing.get_args(tp)
    if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
        if len(value) != len(args):
            raise ConfigError(f"expected {describe(tp)}, got {len(value)} item(s): {_show(value)}", path)
        return tuple(convert(a, v, (*path, i)) for i, (a, v) in enumerate(zip(args, value, strict=True)))
    item = args[0] if args else Any
    items = [convert(item, v, (*path, i)) for i, v in enumerate(value)]
    return list(items) if origin in (list, Sequence) else origin(items)


def _mapping(tp: Any, value: Any, path: tuple[PathPart, ...]) -> Any:
    if value is None:
        value = {}
    if not isinstance(value, Mapping):
        raise _wrong(tp, value, path)
    args = typing.get_args(tp)
    key_tp, val_tp = args if len(args) == 2 else (Any, Any)
    out = {}
    for k, v in value.items():
        if key_tp is str and not isinstance(k, str):
            raise ConfigError(f"keys must be strings (quote it in YAML), got {k!r}", path)
        out[convert(key_tp, k, (*path, str(k)))] = convert(val_tp, v, (*path, str(k)))
    return out


def describe(tp: Any) -> str:
    """A reader's name for an annotation: 'a number', 'an integer or null', "one of 'a', 'b'"."""
    if tp in _NAMES:
        return _NAMES[tp]
    origin = typing.get_origin(tp)
    if origin is Union or isinstance(tp, types.UnionType):
        args = typing.get_args(tp)
        named = [describe(a) for a in args if a is not _NONE]
        return " or ".join(named) + (" or null" if _NONE in args else "")
    if origin is Literal:
        return f"one of {', '.join(repr(c) for c in typing.get_args(tp))}"
    if isinstance(tp, type) and issubclass(tp, enum.Enum):
        return f"one of {', '.join(repr(m.value) for m in tp)}"
    if isinstance(tp, type) and issubclass(tp, PurePath):
        return "a path (string)"
    if dataclasses.is_dataclass(tp) or origin in (dict, Mapping) or tp in (dict, Mapping):
        return "a mapping"
    args = typing.get_args(tp)
    if (origin or tp) is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
        kinds = {describe(a) for a in args}
        what = "numbers" if kinds == {"a number"} else "items"
        return f"a list of {len(args)} {what}"
    return "a list"


_NAMES: dict[Any, str] = {
    bool: "true or false",
    int: "an integer",
    float: "a number",
    str: "a string",
    _NONE: "null",
    Any: "any value",
}


def _wrong(tp: Any, value: Any, path: tuple[PathPart, ...]) -> ConfigError:
    hint = ""
    if isinstance(value, str) and re.fullmatch(r"[-+]?\d+[eE][-+]?\d+", value.strip()):
        fixed = re.sub(r"^([-+]?\d+)", r"\1.0", value.strip())
        hint = f" (YAML reads {value} as text: write {fixed})"
    return ConfigError(f"expected {describe(tp)}, got {_show(value)}{hint}", path)


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


# ---- files ---------------------------------------------------------------------------------------


def read_yaml(path: str | os.PathLike[str], what: str = "config") -> Any:
    """Parse a YAML file; an unreadable file or invalid YAML is one LightstageError line naming it."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise LightstageError(f"{path}: cannot read {what} ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise LightstageError(f"{path}: not a text file (expected YAML)") from None
    return parse_yaml(text, str(path))


def parse_yaml(text: str, source: str) -> Any:
    """Parse YAML text; invalid YAML is one LightstageError line naming `source`."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise LightstageError(f"{source}: invalid YAML: {' '.join(str(e).split())}") from None


def load_file(cls: type[T], path: str | os.PathLike[str], what: str = "config") -> T:
    """`load(cls, <the YAML or JSON file's data>, source=path)`."""
    return load(cls, read_yaml(path, what), str(path))


__all__ = [
    "ConfigError",
    "UnknownKeyError",
    "check_keys",
    "convert",
    "describe",
    "dotted",
    "load",
    "load_file",
    "parse_yaml",
    "read_yaml",
    "require",
    "require_choice",
    "suggest",
]
