"""Validation of configuration files (rig.toml, board.toml, tags.json, model specs, subject files).

The records stay plain frozen dataclasses; their field annotations carry the rules as pydantic
`Annotated` metadata (which nothing else looks at), and `validate` checks a parsed file against
them. Scalars are strict (no "3" for 3, no true for 1, no 2.0 for an integer), `Float` is finite,
and a record whose class sets `__pydantic_config__ = CLOSED` rejects unknown keys. The first
problem becomes one line, by default "KEY: what is wrong", e.g.
"cameras[1].width: expected an integer, got 'wide'":

    fps: Annotated[Float, Field(gt=0)] = 120.0
    drop_rate: Annotated[Float, Field(ge=0, lt=1), worded("must be in [0, 1), got {value}")] = 0.0
    jpeg_quality: between(Int, 1, 100) = 90          # "must be an integer in 1..100, got 900"
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from collections.abc import Callable
from typing import Annotated, Any, NamedTuple, TypeVar

from pydantic import AllowInfNan, ConfigDict, Field, Strict, TypeAdapter, ValidationError, WrapValidator
from pydantic_core import PydanticCustomError

T = TypeVar("T")

Int = Annotated[int, Strict()]
Float = Annotated[float, Strict(), AllowInfNan(False)]   # finite; an integer (fps = 60) counts too
Str = Annotated[str, Strict()]
Bool = Annotated[bool, Strict()]
CLOSED = ConfigDict(extra="forbid")


class Problem(NamedTuple):
    """The first thing wrong with a file: where, pydantic's error type, and the words for it."""

    key: str      # "cameras[1].width" ("" for the file as a whole)
    kind: str     # "missing", "extra_forbidden", "worded", "int_type", ...
    text: str     # "expected an integer, got 'wide'"


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:56] + " ..."


def worded(template: str) -> WrapValidator:
    """Word any error of the annotated value as `template`, where {value} is the value in the file."""

    def wrap(value: Any, handler: Callable[[Any], Any]) -> Any:
        try:
            return handler(value)
        except ValidationError:
            raise PydanticCustomError("worded", template.format(value=_shown(value))) from None

    return WrapValidator(wrap)


def between(tp: Any, low: float, high: float, unit: str = "", low_open: bool = False, high_open: bool = False) -> Any:
    """`tp` (Int or Float) limited to low..high, any error worded with the range and `unit`:
    "must be in (0, 180) degrees, got 0", "must be an integer in 1..100, got 900"."""
    limits = Field(**{"gt" if low_open else "ge": low, "lt" if high_open else "le": high})
    if tp is Int:
        text = f"must be an integer in {low}..{high}"
    else:
        text = f"must be in {'(' if low_open else '['}{low:.15g}, {high:.15g}{')' if high_open else ']'}"
    return Annotated[tp, limits, worded(text + (f" {unit}" if unit else "") + ", got {value}")]


def _reject(value: Any, handler: Callable[[Any], Any]) -> Any:
    raise PydanticCustomError("extra_forbidden", "unknown key")


# A field of the record that the loader fills in (where it was read from), not a key of the file.
NOT_A_KEY = WrapValidator(_reject)

_UNKNOWN_KEY = ("extra_forbidden", "unexpected_keyword_argument")   # a dict's key, a dataclass's key
_WORDS = {
    "missing": "missing",
    "int_type": "expected an integer, got {input}",
    "float_type": "expected a number, got {input}",
    "string_type": "expected a string, got {input}",
    "bool_type": "expected true or false, got {input}",
    "finite_number": "expected a finite number, got {input}",
    "literal_error": "{input} is not one of {expected}",
    "tuple_type": "expected an array, got {type}",
    "list_type": "expected an array, got {type}",
    "dataclass_type": "expected a table, got {type}",
    "dict_type": "expected a table, got {type}",
    "too_short": "expected at least {min_length} values, got {actual_length}",
    "string_too_short": "must not be empty",
    "too_long": "expected at most {max_length} values, got {actual_length}",
    "greater_than": "must be > {gt:g}, got {input}",
    "greater_than_equal": "must be >= {ge:g}, got {input}",
    "less_than": "must be < {lt:g}, got {input}",
    "less_than_equal": "must be <= {le:g}, got {input}",
}


def _bare(tp: Any) -> Any:
    """The type under Annotated and `| None`."""
    while True:
        origin = typing.get_origin(tp)
        if origin is Annotated:
            tp = typing.get_args(tp)[0]
        elif origin in (typing.Union, types.UnionType):
            tp = next(a for a in typing.get_args(tp) if a is not type(None))
        else:
            return tp


def known_keys(tp: Any, path: tuple = ()) -> list[str]:
    """The keys a file may give in the table at `path` (a pydantic loc) below record type `tp`."""
    for part in path:
        tp = _bare(tp)
        if dataclasses.is_dataclass(tp):
            tp = typing.get_type_hints(tp, include_extras=True)[part]
            continue
        args = typing.get_args(tp)
        homogeneous = typing.get_origin(tp) is dict or (len(args) == 2 and args[1] is Ellipsis)
        tp = args[-1 if typing.get_origin(tp) is dict else 0] if homogeneous else args[part]
    tp = _bare(tp)
    if not dataclasses.is_dataclass(tp):
        return []
    hints = typing.get_type_hints(tp, include_extras=True)
    return sorted(f.name for f in dataclasses.fields(tp) if NOT_A_KEY not in getattr(hints[f.name], "__metadata__", ()))


def key_of(loc: tuple) -> str:
    """A pydantic loc as the file spells it: ('cameras', 1, 'sim', 'dist', 0) -> cameras[1].sim.dist[0]."""
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")


def problem_of(error: Any, root: Any) -> Problem:
    """The Problem of one pydantic error (an item of ValidationError.errors()) met validating `root`."""
    kind, loc, value = error["type"], tuple(error["loc"]), error.get("input")
    if kind in _UNKNOWN_KEY:
        kind = "extra_forbidden"
        text = f"unknown key (known: {', '.join(known_keys(root, loc[:-1]))})"
    elif kind in _WORDS:
        text = _WORDS[kind].format(input=_shown(value), type=type(value).__name__, **error.get("ctx", {}))
    else:
        text = error["msg"]
    return Problem(key_of(loc), kind, text)


def _line(problem: Problem) -> str:
    return f"{problem.key}: {problem.text}" if problem.key else problem.text


@functools.cache
def _adapter(tp: Any) -> TypeAdapter:
    return TypeAdapter(tp)


def validate(tp: type[T], doc: Any, source: str, error: type[Exception],
             line: Callable[[Problem], str] = _line) -> T:
    """`doc` (a parsed file) as a `tp`; else raise `error`("SOURCE: " + line(first problem))."""
    try:
        return _adapter(tp).validate_python(doc)
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        # an unknown key is most often a misspelt one, which then also shows up as missing
        first = next((e for e in errors if e["type"] in _UNKNOWN_KEY), errors[0])
        raise error(f"{source}: {line(problem_of(first, tp))}") from None
