"""Typed values for configuration keys: strings from the environment and flags are parsed, TOML
values must already have the field's type; anything else is a ConfigError naming the key."""

from __future__ import annotations

import math
import tomllib
import typing
from typing import Any


class ConfigError(ValueError):
    """A configuration value or key is wrong; the message names the key and its source."""


def parse_literal(text: str) -> Any:
    """A TOML literal (``3e-4``, ``true``, ``[256, 256]``) or, failing that, the plain string."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        return text


_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


def coerce(value: Any, ftype: Any, key: str, source: str) -> Any:
    """Typed value for a field: strings are parsed, TOML values must already have the type."""

    def bad(why: str = "") -> ConfigError:
        want = getattr(ftype, "__name__", str(ftype))
        return ConfigError(f"{source}: {key} = {value!r} is not a valid {want}{why}")

    if ftype == list[float]:
        items = split_list(value) if isinstance(value, str) else value
        if not isinstance(items, list):
            raise bad(" (a list of numbers)")
        return [coerce(i, float, key, source) for i in items]
    if typing.get_origin(ftype) is list:
        items = split_list(value) if isinstance(value, str) else value
        if not isinstance(items, list) or not all(isinstance(i, str) for i in items):
            raise bad(" (a list of strings)")
        return [i.strip() for i in items]
    if ftype is bool:
        if isinstance(value, bool):
            return value
        if isinstance(value, str) and value.strip().lower() in _TRUE | _FALSE:
            return value.strip().lower() in _TRUE
        raise bad(" (true/false)")
    if ftype is int:
        if isinstance(value, str):
            try:
                return int(value.strip().replace("_", ""))
            except ValueError:
                raise bad() from None
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise bad()
    if ftype is float:
        if isinstance(value, str):
            try:
                value = float(value.strip())
            except ValueError:
                raise bad() from None
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        raise bad(" (a finite number)")
    if ftype is str:
        if isinstance(value, str):
            return value
        raise bad()
    raise ConfigError(f"{key}: unsupported field type {ftype!r}")  # a bug in this module


def split_list(text: str) -> list[str]:
    """``"a,b"`` or a TOML array ``'["a", "b"]'``; an empty string is an empty list."""
    text = text.strip()
    if text.startswith("["):
        parsed = parse_literal(text)
        return parsed if isinstance(parsed, list) else [text]
    return [part for part in text.split(",") if part.strip()]
