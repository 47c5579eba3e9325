"""A small typed schema for decoded JSON/TOML, derived from the dataclasses a file is loaded into.

``table_from_dataclass(Cls)`` turns the fields of a dataclass into a :class:`Table` (required =
no default; ``X | None`` = may be absent or null; float/int/bool/str/sequences of floats/nested
dataclasses map to :class:`Number`/:class:`Boolean`/:class:`String`/:class:`Array`/:class:`Table`),
so a field added to the dataclass is in the file format at once. Constraints the type does not say
(ranges, integer limits, infinity allowed) are given per field name. :func:`validate` checks a
decoded document and returns plain Python values (floats, ints, nested lists); errors name the
file, the field path (``agents[0].cost.R[1]``) and what was expected, and unknown keys get a
"did you mean" suggestion.

Booleans are never numbers and strings are never numbers, whatever Python thinks of them.
"""
from __future__ import annotations

import collections.abc
import dataclasses
import difflib
import json
import math
import types
import typing
from dataclasses import dataclass
from typing import Any, Mapping

from .read import InputFileError

INT32_MAX = 2**31 - 1
FLOAT_MAX_INT = int(1.7976931348623157e308)  # larger Python ints do not convert to float


class Invalid(Exception):
    """Raised inside validation; :func:`validate` turns it into the caller's error class."""

    def __init__(self, path: str, message: str):
        super().__init__(path, message)
        self.path, self.message = path, message


def show(value: Any, limit: int = 40) -> str:
    """The value as the file spells it (JSON: null, true, Infinity), cut short for error messages."""
    try:
        text = json.dumps(value, ensure_ascii=False)
    except (TypeError, ValueError):
        text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def suggestion(key: str, allowed: typing.Iterable[str]) -> str:
    """' (did you mean 'dt'?)' or ''."""
    close = difflib.get_close_matches(str(key), sorted(allowed), n=1, cutoff=0.6)
    return f"; did you mean {close[0]!r}?" if close else ""


def unknown_key_message(key: str, allowed: typing.Iterable[str]) -> str:
    allowed = sorted(allowed)
    shown = repr(str(key)) if len(str(key)) <= 40 else repr(str(key)[:37] + "...")
    return f"unknown key {shown}{suggestion(key, allowed)} (allowed: {', '.join(allowed)})"


def _at(path: str, key: str | int) -> str:
    if isinstance(key, int):
        return f"{path}[{key}]"
    return f"{path}.{key}" if path else key


class Spec:
    def check(self, value: Any, path: str) -> Any:
        raise NotImplementedError

    def describe(self) -> str:
        raise NotImplementedError


@dataclass(frozen=True)
class Number(Spec):
    integer: bool = False
    allow_inf: bool = False     # +-inf allowed (NaN never)
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None

    def describe(self, plural: bool = False) -> str:
        if plural:
            kind = "integers" if self.integer else ("numbers (+-Infinity allowed)" if self.allow_inf else "finite numbers")
        else:
            kind = "an integer" if self.integer else ("a number (+-Infinity allowed)" if self.allow_inf else "a finite number")
        bounds = [f"{op} {b}" for op, b in ((">=", self.ge), (">", self.gt), ("<=", self.le), ("<", self.lt)) if b is not None]
        return kind + (" " + " and ".join(bounds) if bounds else "")

    def check(self, value: Any, path: str) -> Any:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise Invalid(path, f"expected {self.describe()}, got {show(value)}")
        if self.integer and not isinstance(value, int):
            raise Invalid(path, f"expected {self.describe()}, got {show(value)}")
        if isinstance(value, int) and not self.integer and abs(value) > FLOAT_MAX_INT:
            raise Invalid(path, f"expected {self.describe()}, got an integer too large for a float")
        if isinstance(value, float) and (math.isnan(value) or (math.isinf(value) and not self.allow_inf)):
            raise Invalid(path, f"expected {self.describe()}, got {show(value)}")
        if ((self.ge is not None and not value >= self.ge) or (self.gt is not None and not value > self.gt)
                or (self.le is not None and not value <= self.le) or (self.lt is not None and not value < self.lt)):
            raise Invalid(path, f"expected {self.describe()}, got {show(value)}")
        return value if self.integer else float(value)


@dataclass(frozen=True)
class Boolean(Spec):
    def describe(self) -> str:
        return "true or false"

    def check(self, value: Any, path: str) -> bool:
        if not isinstance(value, bool):
            raise Invalid(path, f"expected true or false, got {show(value)}")
        return value


@dataclass(frozen=True)
class String(Spec):
    choices: tuple[str, ...] | None = None
    nonempty: bool = False
    max_len: int = 10_000

    def describe(self) -> str:
        if self.choices:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        return "a non-empty string" if self.nonempty else "a string"

    def check(self, value: Any, path: str) -> str:
        if not isinstance(value, str) or (self.nonempty and not value) or len(value) > self.max_len:
            raise Invalid(path, f"expected {self.describe()}, got {show(value)}")
        if self.choices and value not in self.choices:
            raise Invalid(path, f"expected {self.describe()}, got {show(value)}{suggestion(value, self.choices)}")
        return value


@dataclass(frozen=True)
class Array(Spec):
    """A rectangular nested list of numbers with ``ndim`` levels; ``length`` fixes the outer size."""

    ndim: int = 1
    item: Number = Number()
    length: int | None = None
    min_len: int = 0

    def describe(self) -> str:
        what = ("a list of " if self.ndim == 1 else f"a {self.ndim}-D nested list of ") + self.item.describe(plural=True)
        return what if self.length is None else f"{what} of length {self.length}"

    def check(self, value: Any, path: str) -> list:
        return self._check(value, path, self.ndim, None, outer=True)

    def _check(self, value: Any, path: str, ndim: int, shape: list | None, outer: bool) -> list:
        if not isinstance(value, list):
            raise Invalid(path, f"expected {self.describe() if outer else 'a list'}, got {show(value)}")
        if outer and self.length is not None and len(value) != self.length:
            raise Invalid(path, f"expected {self.length} values, got {len(value)}")
        if outer and len(value) < self.min_len:
            raise Invalid(path, f"expected at least {self.min_len} values, got {len(value)}")
        if ndim == 1:
            return [self.item.check(v, f"{path}[{i}]") for i, v in enumerate(value)]
        rows = [self._check(v, f"{path}[{i}]", ndim - 1, None, False) for i, v in enumerate(value)]
        if rows and any(len(r) != len(rows[0]) for r in rows):
            i = next(i for i, r in enumerate(rows) if len(r) != len(rows[0]))
            raise Invalid(f"{path}[{i}]", f"rows must all have {len(rows[0])} values (rectangular), got {len(rows[i])}")
        return rows


@dataclass(frozen=True)
class ListOf(Spec):
    item: Spec
    min_len: int = 0
    max_len: int | None = None

    def describe(self) -> str:
        return f"a list of ({self.item.describe()})"

    def check(self, value: Any, path: str) -> list:
        if not isinstance(value, list):
            raise Invalid(path, f"expected a list, got {show(value)}")
        if len(value) < self.min_len:
            raise Invalid(path, f"expected at least {self.min_len} entries, got {len(value)}")
        if self.max_len is not None and len(value) > self.max_len:
            raise Invalid(path, f"expected at most {self.max_len} entries, got {len(value)}")
        return [self.item.check(v, f"{path}[{i}]") for i, v in enumerate(value)]


@dataclass(frozen=True)
class AnyOf(Spec):
    options: tuple[Spec, ...]

    def describe(self) -> str:
        return " or ".join(o.describe() for o in self.options)

    def check(self, value: Any, path: str) -> Any:
        errors = []
        for option in self.options:
            try:
                return option.check(value, path)
            except Invalid as exc:
                errors.append(exc)
        # The option whose error is deepest inside the value is the one the writer meant.
        deepest = max(errors, key=lambda e: len(e.path))
        if deepest.path != path:
            raise deepest
        raise Invalid(path, f"expected {self.describe()}, got {show(value)}")


@dataclass(frozen=True)
class FieldSpec:
    spec: Spec
    required: bool = True
    nullable: bool = False      # null means absent


@dataclass(frozen=True)
class Table(Spec):
    fields: Mapping[str, FieldSpec]
    name: str = "object"

    def describe(self) -> str:
        return f"an object with keys {', '.join(self.fields)}"

    def check(self, value: Any, path: str) -> dict:
        if not isinstance(value, dict):
            raise Invalid(path, f"expected {self.describe()}, got {show(value)}")
        for key in value:
            if key not in self.fields:
                raise Invalid(_at(path, key), unknown_key_message(key, self.fields))
        out = {}
        for key, f in self.fields.items():
            where = _at(path, key)
            if key not in value or (value[key] is None and f.nullable):
                if f.required:
                    raise Invalid(where, f"missing (expected {f.spec.describe()})")
                continue
            out[key] = f.spec.check(value[key], where)
        return out


@dataclass(frozen=True)
class Tagged(Spec):
    """An object whose ``tag`` key picks one of several tables (e.g. dynamics ``type``)."""

    tag: str
    variants: Mapping[str, Table]

    def describe(self) -> str:
        return f"an object with {self.tag!r} one of {', '.join(map(repr, self.variants))}"

    def check(self, value: Any, path: str) -> dict:
        if not isinstance(value, dict):
            raise Invalid(path, f"expected {self.describe()}, got {show(value)}")
        if self.tag not in value:
            raise Invalid(_at(path, self.tag), f"missing (expected one of {', '.join(map(repr, self.variants))})")
        kind = String(choices=tuple(self.variants)).check(value[self.tag], _at(path, self.tag))
        body = {k: v for k, v in value.items() if k != self.tag}
        return {self.tag: kind, **self.variants[kind].check(body, path)}


def validate(data: Any, spec: Spec, source: str, error: type[InputFileError] = InputFileError) -> Any:
    """Check ``data`` against ``spec``; raise ``error("SOURCE: PATH: what was expected")``."""
    try:
        return spec.check(data, "")
    except Invalid as exc:
        raise error(f"{source}: {exc.path or '<top level>'}: {exc.message}") from None


def _spec_for_type(tp: Any, name: str) -> tuple[Spec, bool]:
    """(spec, nullable) for a type annotation."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        nullable = len(args) < len(typing.get_args(tp))
        specs = [_spec_for_type(a, name)[0] for a in args]
        return (specs[0] if len(specs) == 1 else AnyOf(tuple(specs))), nullable
    if tp is bool:
        return Boolean(), False
    if tp is int:
        return Number(integer=True, ge=-INT32_MAX, le=INT32_MAX), False
    if tp is float:
        return Number(), False
    if tp is str:
        return String(), False
    if dataclasses.is_dataclass(tp):
        return table_from_dataclass(tp), False
    if origin in (list, tuple, collections.abc.Sequence):
        (item, *_rest) = typing.get_args(tp) or (float,)
        if item in (float, int):
            return Array(1, Number(integer=item is int)), False
        return ListOf(_spec_for_type(item, name)[0]), False
    raise TypeError(f"field {name!r}: no schema for type {tp!r}; give one in `overrides`")


def table_from_dataclass(cls: type, overrides: Mapping[str, Spec] | None = None,
                         extra: Mapping[str, FieldSpec] | None = None, exclude: typing.Iterable[str] = (),
                         nullable: typing.Iterable[str] = ()) -> Table:
    """The file form of a dataclass: one key per init field (minus ``exclude``), with ``overrides``
    replacing the spec derived from a field's type, ``extra`` adding file-only keys and ``nullable``
    naming defaulted fields whose ``null`` means "absent" although their type has no None."""
    overrides = dict(overrides or {})
    null_ok = set(nullable)
    hints = typing.get_type_hints(cls)
    out: dict[str, FieldSpec] = {}
    for f in dataclasses.fields(cls):
        if not f.init or f.name in exclude:
            continue
        spec, nullable = _spec_for_type(hints[f.name], f"{cls.__name__}.{f.name}") if f.name not in overrides \
            else (overrides.pop(f.name), _is_optional(hints[f.name]))
        required = f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
        out[f.name] = FieldSpec(spec, required=required, nullable=nullable or f.name in null_ok)
    if overrides:
        raise TypeError(f"{cls.__name__}: overrides for unknown fields {sorted(overrides)}")
    out.update(extra or {})
    return Table(out, cls.__name__)


def _is_optional(tp: Any) -> bool:
    return typing.get_origin(tp) in (typing.Union, types.UnionType) and type(None) in typing.get_args(tp)

__all__ = ["AnyOf", "Array", "Boolean", "FieldSpec", "Invalid", "ListOf", "Number", "Spec", "String", "Table",
           "Tagged", "table_from_dataclass", "show", "suggestion", "unknown_key_message", "validate"]
