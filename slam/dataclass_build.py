"""Typed dataclasses from plain mappings (a recipe's sections): values coerced to the
field types, unknown keys listed, moved keys upgraded with one warning."""

from __future__ import annotations

import copy
import dataclasses
import re
import types
import typing
import warnings
from typing import Any

from slam.errors import ConfigError

# a number in exponent form without a dot (1e-3), which YAML 1.1 leaves a string
_FLOAT = re.compile(r"[+-]?(\d+\.?\d*|\.\d+)[eE][+-]?\d+")


class ConfigDeprecationWarning(FutureWarning):
    """A recipe key that still works but has moved; the message names its new place."""


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, where: str, base: Any = None) -> Any:
    """Check/convert one value against a type hint; raise ConfigError naming ``where``.
    base: the value a mapping for a dataclass completes (its fields not in the mapping)."""
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, where, base)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(errors[0] if errors else f"{where}: bad value {value!r}")
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return build_dataclass(tp, value, where, base if isinstance(base, tp) else None)
    if origin in (list, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        args = typing.get_args(tp)
        inner = args[0] if args else Any
        items = [_coerce(v, inner, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        return dict(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where}: expected true/false, got {value!r}")
    if tp is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return float(value)
        if isinstance(value, str) and _FLOAT.fullmatch(value.strip()):
            return float(value)  # YAML 1.1 reads 1e-3 (no dot) as a string
        raise ConfigError(f"{where}: expected a number, got {value!r}")
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():
            return int(value)
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if tp is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{where}: expected a string, got {value!r}")
    return value


def upgrade_keys(cls: type, data: dict[str, Any], where: str) -> dict[str, Any]:
    """``data`` with the keys ``cls.deprecated_keys`` maps (old key -> new dotted path) moved
    to their new place, and one ConfigDeprecationWarning naming each new key. An old key
    that is also a field of ``cls`` counts as old when its value is not a mapping."""
    moved: dict[str, str] = getattr(cls, "deprecated_keys", None) or {}
    fields = {f.name for f in dataclasses.fields(cls)}
    old = [k for k in data if k in moved and not (k in fields and isinstance(data[k], dict))]
    if not old:
        return data
    out = {k: copy.deepcopy(v) for k, v in data.items() if k not in old}
    for k in old:
        *sections, leaf = moved[k].split(".")
        node = out
        for section in sections:
            node = node.setdefault(section, {})
            if not isinstance(node, dict):
                raise ConfigError(f"'{where}.{section}' must be a mapping (for '{where}.{k}')")
        if leaf in node:
            raise ConfigError(f"'{where}.{k}' and '{where}.{moved[k]}' are both set: keep one")
        node[leaf] = data[k]
    renames = ", ".join(f"{k} -> {moved[k]}" for k in old)
    warnings.warn(
        f"'{where}': these keys have moved and stop working in the next version; "
        f"write them nested: {renames}",
        ConfigDeprecationWarning,
        stacklevel=3,
    )
    return out


def _field_default(f: dataclasses.Field) -> Any:
    """A field's default value (a fresh one from its default_factory), None without one."""
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None if f.default is dataclasses.MISSING else f.default


def build_dataclass(
    cls: type, data: dict[str, Any] | None, where: str = "config", base: Any = None
) -> Any:
    """Instantiate dataclass ``cls`` from ``data``, rejecting unknown keys with the valid list
    (moved keys of ``cls.deprecated_keys`` are upgraded first, with a warning).

    The fields ``data`` does not give keep the values of ``base`` (a ``cls`` instance:
    the default its parent section gives it), else ``cls``'s defaults; a nested section
    given in part overrides only its given fields of that default, at any depth.
    """
    data = upgrade_keys(cls, dict(data or {}), where)
    hints = typing.get_type_hints(cls)
    valid = [f.name for f in dataclasses.fields(cls) if f.init]
    unknown = sorted(set(data) - set(valid))
    if unknown:
        raise ConfigError(
            f"unknown key{'s' if len(unknown) > 1 else ''} "
            + ", ".join(f"'{where}.{k}'" for k in unknown)
            + f"; valid keys of '{where}': {', '.join(valid)}"
        )
    fields = {f.name: f for f in dataclasses.fields(cls)}
    kwargs = {}
    for k, v in data.items():
        default = None
        if isinstance(v, dict):  # a section: completed from the parent's default for it
            default = getattr(base, k) if base is not None else _field_default(fields[k])
        kwargs[k] = _coerce(v, hints[k], f"{where}.{k}", default)
    try:
        return cls(**kwargs) if base is None else dataclasses.replace(base, **kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{where}: {exc}") from exc
