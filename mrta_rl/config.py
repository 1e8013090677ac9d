"""One declaration per parameter: its type with a range or choices, checked before any work.

A parameter is declared once, where it is defined: a keyword argument of a learner's
``__init__`` (the signature is the schema of ``conf/learner/<name>.yaml``) or a field of a
dataclass (``AuctionParams``, the run settings), annotated with its type and, through
``typing.Annotated``, its range or choices::

    alpha: Annotated[float, Range(0, 1, low_open=True)] = 0.1   # in (0, 1]
    epsilon_decay_episodes: Annotated[int, Range(0)] = 20       # integer >= 0
    target_update: Literal["soft", "hard"] = "soft"             # choices
    prior: Annotated[str | None, Choices("spread", "greedy")] = None

Supported types: ``bool``, ``int`` (not bool, within 64 bits), ``float`` (int accepted, finite),
``str``, ``Literal[...]``, ``X | None``, fixed-length ``tuple[...]`` and any-length
``tuple[X, ...]`` (a list or tuple in a config; a ``Range`` or ``Choices`` applies to each
item). Any other annotation is not a hyperparameter's (the runner supplies ``env``, ``rng``,
``partition`` and ``base_policy``: :data:`RUNNER_ARGUMENTS`) and is not checked.

:func:`check_value` checks one value, :func:`check_keywords` a config mapping against a class's
``__init__`` (following ``**kwargs`` up the base classes) or a function, :func:`check_fields`
against a dataclass, :func:`check_arguments` a command line's options against a dataclass.
Every message names the key (or the option) and what is allowed, e.g.
``learner.alpha_power: must be a number >= 0, got -2``.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
import numbers
import reprlib
import types
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Union

__all__ = [
    "Annotated",
    "Choices",
    "ConfigError",
    "Declared",
    "Range",
    "UserError",
    "check_arguments",
    "check_fields",
    "check_keywords",
    "check_value",
    "declared_fields",
    "declared_keywords",
    "describe",
    "short_list",
]

# supplied by the runner, not the config: the env, the generator, the subG partition, and the
# trained learner a setting names by its run dir (``Learner.base_run``)
RUNNER_ARGUMENTS = frozenset({"env", "rng", "partition", "base_policy"})


class UserError(ValueError):
    """Bad input from the user (config, system file, checkpoint path): a message, no traceback.

    The scripts' wrapper (``mrta_rl.runners.cli``) prints the message alone and exits non-zero;
    every other exception is a bug and keeps its traceback.
    """


class ConfigError(UserError):
    """A setting is unknown, of the wrong type, out of range or not one of its choices."""


@dataclass(frozen=True)
class Range:
    """Allowed interval of a number: ``low <= x <= high``; ``None`` = unbounded on that side.

    Attributes:
        low: Lower bound, or None.
        high: Upper bound, or None.
        low_open: Exclude ``low`` (``x > low``).
        high_open: Exclude ``high`` (``x < high``).
    """

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def contains(self, x: float) -> bool:
        """True if ``x`` is inside (NaN never is)."""
        if isinstance(x, float) and math.isnan(x):
            return False
        if self.low is not None and (x <= self.low if self.low_open else x < self.low):
            return False
        return not (self.high is not None and (x >= self.high if self.high_open else x > self.high))

    def describe(self) -> str:
        """``">= 0"``, ``"in (0, 1]"``..."""
        if self.low is not None and self.high is not None:
            left, right = "(" if self.low_open else "[", ")" if self.high_open else "]"
            return f"in {left}{_num(self.low)}, {_num(self.high)}{right}"
        if self.low is not None:
            return f"{'>' if self.low_open else '>='} {_num(self.low)}"
        if self.high is not None:
            return f"{'<' if self.high_open else '<='} {_num(self.high)}"
        return ""


# an integer setting is held as numpy's and torch's int64 (counts, sizes, seeds): larger ones
# would overflow where they are used
INT64 = Range(-(2**63), 2**63 - 1)


class Choices:
    """Allowed values of a setting (for a ``str``; ``Literal`` does the same inline)."""

    def __init__(self, *values: Any) -> None:
        """Keep the allowed values, in the order the message lists them."""
        self.values = tuple(values)

    def __repr__(self) -> str:
        return f"Choices{self.values!r}"


@dataclass(frozen=True)
class Declared:
    """One declared parameter: name, annotation (with its ``Annotated`` extras) and default."""

    name: str
    annotation: Any
    default: Any = inspect.Parameter.empty

    @property
    def required(self) -> bool:
        """True when the declaration has no default."""
        return self.default is inspect.Parameter.empty


def short_list(items: Iterable[Any], first: int = 5, *, quote: bool = False) -> str:
    """A list as messages print it: the first items, then a count of the rest.

    A message stays one short line however long the list it names (a file's keys, a team's
    robots): ``short_list(names)`` is ``"bias, h_within_3, h_within_10, queued_h, queued_l and
    33 more"``.

    Args:
        items: The items (shown with ``str``).
        first: How many items are shown before the count.
        quote: Show the items with ``repr`` (``'R1', 'R2'``).

    Returns:
        The items joined by commas, cut after ``first`` with ``"and N more"``; ``"none"`` if empty.
    """
    items = list(items)
    if not items:
        return "none"
    shown = ", ".join(repr(item) if quote else str(item) for item in items[:first])
    rest = len(items) - first
    return f"{shown} and {rest} more" if rest > 0 else shown


def _num(x: float) -> str:
    if isinstance(x, float) and x.is_integer() and abs(x) < 1e15:
        return str(int(x))
    return repr(x) if isinstance(x, float) else str(x)


def _split(annotation: Any) -> tuple[Any, list[Any]]:
    """``Annotated[T, a, b]`` -> ``(T, [a, b])``; anything else -> ``(annotation, [])``."""
    if typing.get_origin(annotation) is Annotated:
        return annotation.__origin__, list(annotation.__metadata__)
    return annotation, []


def _union_members(tp: Any) -> tuple[Any, ...] | None:
    if typing.get_origin(tp) in (Union, types.UnionType):
        return typing.get_args(tp)
    return None


def is_checked(annotation: Any) -> bool:
    """True if :func:`check_value` understands the annotation (a hyperparameter's type)."""
    tp, _ = _split(annotation)
    members = _union_members(tp)
    if members is not None:
        return all(m is type(None) or is_checked(m) for m in members)
    if typing.get_origin(tp) is Literal or tp in (bool, int, float, str):
        return True
    if typing.get_origin(tp) is tuple:
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        return bool(args) and all(is_checked(a) for a in args)
    return False


def _is_list(tp: Any) -> bool:
    """``tuple[X, ...]``: a list of any length (a Range or Choices applies to each item)."""
    args = typing.get_args(tp)
    return typing.get_origin(tp) is tuple and len(args) == 2 and args[1] is Ellipsis


def describe(annotation: Any) -> str:
    """What a value of this declared type may be, as the messages say it."""
    tp, extras = _split(annotation)
    ranges = [e for e in extras if isinstance(e, Range)]
    choices = [e for e in extras if isinstance(e, Choices)]
    members = _union_members(tp)
    if members is not None:
        inner = [m for m in members if m is not type(None)]
        core = describe(_rebuild(inner, extras))
        return f"{core} or null" if type(None) in members else core
    if _is_list(tp):
        item = typing.get_args(tp)[0]
        return "a list, each item " + describe(Annotated[(item, *extras)] if extras else item)
    if choices:
        return "one of " + ", ".join(repr(c) for c in choices[0].values)
    if typing.get_origin(tp) is Literal:
        return "one of " + ", ".join(repr(c) for c in typing.get_args(tp))
    bound = f" {ranges[0].describe()}" if ranges and ranges[0].describe() else ""
    if tp is bool:
        return "true or false"
    if tp is int:
        return f"an integer{bound}"
    if tp is float:
        return f"a number{bound}"
    if tp is str:
        return "a string"
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        kinds = {describe(a) for a in args}
        what = "integers" if kinds == {"an integer"} else "values"
        return f"a list of {len(args)} {what}{bound}"
    return f"a {getattr(tp, '__name__', tp)}"


def _rebuild(members: list[Any], extras: list[Any]) -> Any:
    """The union of ``members`` with the ``Annotated`` extras put back (for :func:`describe`)."""
    tp = members[0] if len(members) == 1 else Union[tuple(members)]  # noqa: UP007
    return Annotated[(tp, *extras)] if extras else tp


def _fail(key: str, annotation: Any, value: Any) -> ConfigError:
    beyond = _is_int(value) and not INT64.contains(value)
    note = " (more than 64 bits hold)" if beyond else ""
    return ConfigError(f"{key}: must be {describe(annotation)}, got {reprlib.repr(value)}{note}")


def _is_int(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_finite(value: Any) -> bool:
    """A real number that is finite (an integer past the floats is not)."""
    try:
        return (
            isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
        )
    except OverflowError:
        return False


def check_value(key: str, value: Any, annotation: Any) -> Any:
    """Check one value against its declared type and range or choices.

    Args:
        key: The setting's full name for the message (``learner.alpha``).
        value: The value (plain Python, as ``OmegaConf.to_container`` gives it).
        annotation: The declared type (possibly ``Annotated``).

    Returns:
        The value, lists turned into tuples for ``tuple`` types.

    Raises:
        ConfigError: naming the key, what is allowed and the value.
    """
    tp, extras = _split(annotation)
    members = _union_members(tp)
    if members is not None:
        if value is None and type(None) in members:
            return None
        inner = [m for m in members if m is not type(None)]
        for member in inner:
            try:
                return check_value(key, value, _rebuild([member], extras))
            except ConfigError:
                continue
        raise _fail(key, annotation, value)
    if _is_list(tp):
        item = typing.get_args(tp)[0]
        if not isinstance(value, (list, tuple)):
            raise _fail(key, annotation, value)
        try:
            return tuple(
                check_value(key, v, Annotated[(item, *extras)] if extras else item) for v in value
            )
        except ConfigError:
            raise _fail(key, annotation, value) from None
    for extra in extras:
        if isinstance(extra, Choices) and value not in extra.values:
            raise _fail(key, annotation, value)
    if typing.get_origin(tp) is Literal:
        if value not in typing.get_args(tp) or isinstance(value, bool):
            raise _fail(key, annotation, value)
        return value
    ranges = [e for e in extras if isinstance(e, Range)]
    if typing.get_origin(tp) is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            raise _fail(key, annotation, value)
        try:
            return tuple(
                check_value(key, v, Annotated[(a, *extras)] if extras else a)
                for v, a in zip(value, args, strict=True)
            )
        except ConfigError:
            raise _fail(key, annotation, value) from None
    ok = {
        bool: lambda v: isinstance(v, bool),
        int: lambda v: _is_int(v) and INT64.contains(v),
        float: _is_finite,
        str: lambda v: isinstance(v, str),
    }.get(tp)
    if ok is None:
        return value  # not a hyperparameter's type (see module docstring)
    if not ok(value) or (ranges and not all(r.contains(value) for r in ranges)):
        raise _fail(key, annotation, value)
    return value


def _hints(obj: Any) -> dict[str, Any]:
    try:
        return typing.get_type_hints(obj, include_extras=True)
    except (NameError, TypeError):  # an annotation only importable under TYPE_CHECKING
        return {}


def declared_keywords(target: type | Callable[..., Any]) -> dict[str, Declared]:
    """The keyword parameters a class's ``__init__`` (or a function) takes, with their types.

    For a class, ``**kwargs`` of an ``__init__`` are followed up the method resolution order, so
    a subclass that passes ``**hyperparameters`` to its base declares the base's parameters too.
    The runner's own arguments (:data:`RUNNER_ARGUMENTS`) are left out.

    Args:
        target: A class or a function.

    Returns:
        ``{name: Declared}`` in signature order, subclass parameters first.
    """
    functions = (
        [k.__dict__["__init__"] for k in target.__mro__ if "__init__" in k.__dict__]
        if isinstance(target, type)
        else [target]
    )
    out: dict[str, Declared] = {}
    for function in functions:
        if function is object.__init__:
            break
        hints = _hints(function)
        more = False
        for p in inspect.signature(function).parameters.values():
            if p.kind is p.VAR_KEYWORD:
                more = True
            elif p.name != "self" and p.kind in (p.KEYWORD_ONLY, p.POSITIONAL_OR_KEYWORD):
                if p.name not in out and p.name not in RUNNER_ARGUMENTS:
                    out[p.name] = Declared(p.name, hints.get(p.name, Any), p.default)
        if not more:
            break
    return out


def declared_fields(cls: type) -> dict[str, Declared]:
    """The fields of a dataclass with their declared types and defaults."""
    hints = _hints(cls)
    out = {}
    for f in dataclasses.fields(cls):
        default = (
            f.default
            if f.default is not dataclasses.MISSING
            else (
                f.default_factory()
                if f.default_factory is not dataclasses.MISSING
                else inspect.Parameter.empty
            )
        )
        out[f.name] = Declared(f.name, hints.get(f.name, Any), default)
    return out


def _check_mapping(
    declared: dict[str, Declared],
    values: Mapping[str, Any],
    prefix: str,
    owner: str,
    *,
    require: bool,
    null_is_default: bool = False,
) -> dict[str, Any]:
    """Unknown keys, then each value's type and range; missing keys when ``require``."""
    if not isinstance(values, Mapping):
        raise ConfigError(
            f"{prefix or 'config'}: must be a mapping of settings, got {reprlib.repr(values)}"
        )
    path = f"{prefix}." if prefix else ""
    for key in values:
        if key not in declared:
            known = f"known: {short_list(declared)}" if declared else "it takes none"
            raise ConfigError(f"{path}{key}: unknown setting of {owner} ({known})")
    out = {}
    for name, decl in declared.items():
        if name in values and values[name] is None and null_is_default:
            continue
        if name in values:
            out[name] = check_value(f"{path}{name}", values[name], decl.annotation)
        elif require and decl.required:
            raise ConfigError(f"{path}{name}: missing; must be {describe(decl.annotation)}")
    return out


def check_keywords(
    target: type | Callable[..., Any], values: Mapping[str, Any], prefix: str
) -> dict[str, Any]:
    """Check config settings against the keyword parameters of a class or function.

    Args:
        target: A learner class (its ``__init__``) or a function such as ``random_system``.
        values: The settings (plain Python); Hydra's ``_target_`` / ``_partial_`` are skipped.
        prefix: Config path for the messages (``learner``).

    Returns:
        The checked settings.

    Raises:
        ConfigError: on an unknown key or a value of the wrong type, range or choice.
    """
    values = {k: v for k, v in values.items() if k not in ("_target_", "_partial_")}
    owner = getattr(target, "__name__", str(target))
    return _check_mapping(declared_keywords(target), values, prefix, owner, require=False)


def check_fields(
    cls: type,
    values: Mapping[str, Any],
    prefix: str,
    *,
    require: bool = False,
    null_is_default: bool = False,
) -> dict[str, Any]:
    """Check config settings against the declared fields of a dataclass.

    Args:
        cls: The dataclass.
        values: The settings (plain Python).
        prefix: Config path for the messages (``env``, ``train``).
        require: Also refuse a missing field that has no default.
        null_is_default: A ``None`` value means "the default" (``conf/env/auction.yaml``): it is
            left out of the result instead of checked.

    Returns:
        The checked settings.

    Raises:
        ConfigError: on an unknown or missing key or a value of the wrong type, range or choice.
    """
    return _check_mapping(
        declared_fields(cls),
        values,
        prefix,
        cls.__name__,
        require=require,
        null_is_default=null_is_default,
    )


def check_arguments(cls: type, arguments: Any) -> dict[str, Any]:
    """Check a command line's parsed options against the declared fields of a dataclass.

    Field ``batch_sizes`` is the option ``--batch-sizes`` (``argparse`` stores it as
    ``batch_sizes``), and the messages name the option as typed.

    Args:
        cls: The dataclass declaring the options' types and ranges.
        arguments: The parsed options (an ``argparse.Namespace``).

    Returns:
        The checked values by field name.

    Raises:
        ConfigError: naming the option (``--seconds: must be a number > 0, got nan``).
    """
    return {
        name: check_value(
            f"--{name.replace('_', '-')}", getattr(arguments, name), declared.annotation
        )
        for name, declared in declared_fields(cls).items()
    }
