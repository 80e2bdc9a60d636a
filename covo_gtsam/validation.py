"""Declared settings and their checks; each failure is a :class:`ConfigError` naming the setting.

A settings class (a frozen dataclass) declares each field with :func:`flag`, :func:`integer`,
:func:`number` or :func:`choice`: its default, unit, allowed range and a one-line description,
kept in the field's metadata. :func:`check_settings`, called by the class's ``__post_init__``,
checks every field against that declaration; :func:`range_text` states the range for the
documentation (docs/configuration.md is generated from the same metadata).

Booleans are not numbers here (``True`` is no pixel sigma) and numbers are not booleans (the
string ``"false"`` is no ``False``); numpy scalars count as the Python type they stand for.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from enum import Enum

import numpy as np

from .errors import ConfigError

#: Sanity limits shared by the configurations and the command line: beyond them the models are
#: meaningless and float arithmetic overflows. Pixel noise in pixels, covariance scales (phi,
#: kappa) as factors, depth units per metre.
MIN_PIXEL_SIGMA, MAX_PIXEL_SIGMA = 0.01, 1e4
MIN_SCALE, MAX_SCALE = 1e-6, 1e6
MIN_DEPTH_SCALE, MAX_DEPTH_SCALE = 1e-3, 1e9


def is_int(value) -> bool:
    """An integer (Python or numpy), not a bool."""
    return isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))


def is_real(value) -> bool:
    """A real number (Python or numpy int/float), not a bool; may be NaN or inf."""
    return isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_))


def check_bool(name: str, value) -> None:
    if not isinstance(value, (bool, np.bool_)):
        raise ConfigError(f"{name} must be true or false, got {value!r}")


def check_int(name: str, value, minimum: int, maximum: int | None = None) -> None:
    """An integer in ``[minimum, maximum]`` (no upper limit if None)."""
    if is_int(value) and value >= minimum and (maximum is None or value <= maximum):
        return
    if maximum is None:
        raise ConfigError(f"{name} must be an integer >= {minimum}, got {value!r}")
    raise ConfigError(f"{name} must be an integer from {minimum} to {maximum}, got {value!r}")


def check_real(name: str, value, kind: str, minimum: float | None = None, maximum: float | None = None,
               finite: bool = True) -> None:
    """A real number; ``kind`` is ``"positive"`` (> 0), ``"non-negative"`` (>= 0) or ``"any"``;
    optionally within ``[minimum, maximum]``; NaN never, inf only if not ``finite``."""
    ok = is_real(value) and not math.isnan(value) and (math.isfinite(value) or not finite)
    if ok:
        ok = {"positive": value > 0, "non-negative": value >= 0, "any": True}[kind]
        ok = ok and (minimum is None or value >= minimum) and (maximum is None or value <= maximum)
    if ok:
        return
    what = "a finite" if finite and kind == "any" else ("a" if kind == "any" else f"a {kind}")
    what += " number"
    if minimum is not None and maximum is not None:
        what += f" from {minimum:g} to {maximum:g}"
    elif minimum is not None:
        what += f" >= {minimum:g}"
    elif maximum is not None:
        what += f" <= {maximum:g}"
    raise ConfigError(f"{name} must be {what}, got {value!r}")


def check_choice(name: str, value, allowed: tuple) -> None:
    if not any(value is a or (isinstance(value, str) and value == a) for a in allowed):
        raise ConfigError(f"unknown {name} {value!r}; choose one of {allowed}")


def parse_choice(name: str, value, choices: type[Enum], optional: bool = False):
    """``value`` (a member of ``choices`` or its string) as the member; with ``optional`` also None
    (given as None, ``"none"`` or ``""``: TOML has no null). ConfigError as :func:`check_choice`."""
    if optional and (value is None or (isinstance(value, str) and value in ("", "none"))):
        return None
    check_choice(name, value, tuple(c.value for c in choices) + (("none",) if optional else ()))
    return choices(value)


# -- declared settings ------------------------------------------------------------------------------

def flag(default: bool, doc: str):
    """A true/false setting."""
    return dataclasses.field(default=default, metadata={"kind": "bool", "doc": doc, "unit": ""})


def integer(default: int | None, doc: str, minimum: int = 0, maximum: int | None = None, unit: str = "",
            values: tuple[int, ...] | None = None, optional: bool = False):
    """An integer in ``[minimum, maximum]`` (no upper limit if None), or one of ``values``; with
    ``optional`` also None (unset)."""
    return dataclasses.field(default=default, metadata={
        "kind": "int", "doc": doc, "unit": unit, "minimum": minimum, "maximum": maximum, "values": values,
        "optional": optional})


def number(default: float, doc: str, unit: str, sign: str = "positive", minimum: float | None = None,
           maximum: float | None = None, above: float | None = None, finite: bool = True):
    """A real number: ``sign`` ``"positive"`` (> 0), ``"non-negative"`` (>= 0) or ``"any"``, within
    ``[minimum, maximum]`` (None: unbounded on that side); ``above``: instead, a number ``> above``
    and ``<= maximum``. NaN never, inf only if not ``finite``."""
    return dataclasses.field(default=default, metadata={
        "kind": "real", "doc": doc, "unit": unit, "sign": sign, "minimum": minimum, "maximum": maximum,
        "above": above, "finite": finite})


def choice(default, doc: str, choices: type[Enum], optional: bool = False):
    """One of the members of the enum ``choices`` (its string value is accepted); with ``optional``
    also None."""
    return dataclasses.field(default=default, metadata={
        "kind": "choice", "doc": doc, "unit": "", "choices": choices, "optional": optional})


def declared(cls_or_obj) -> list[dataclasses.Field]:
    """The declared settings (fields made by :func:`flag`, :func:`integer`, :func:`number`,
    :func:`choice`) of a settings class or object, in order."""
    return [f for f in dataclasses.fields(cls_or_obj) if "kind" in f.metadata]


def check_settings(obj, section: str = "") -> None:
    """Check every declared setting of the dataclass ``obj``; :class:`ConfigError` naming it as
    ``section.name`` (``name`` without a section). A choice given as its string becomes the enum
    member (``obj`` may be frozen)."""
    for f in declared(obj):
        meta, value = f.metadata, getattr(obj, f.name)
        name = f"{section}.{f.name}" if section else f.name
        kind = meta["kind"]
        if kind == "bool":
            check_bool(name, value)
        elif kind == "int":
            if value is None and meta["optional"]:
                continue
            values = meta["values"]
            if values is None:
                check_int(name, value, meta["minimum"], meta["maximum"])
            elif not (is_int(value) and value in values):
                listed = ", ".join(map(str, values[:-1])) + f" or {values[-1]}"
                raise ConfigError(f"{name} must be {listed}, got {value!r}")
        elif kind == "real":
            above, maximum = meta["above"], meta["maximum"]
            if above is None:
                check_real(name, value, meta["sign"], meta["minimum"], maximum, meta["finite"])
            elif not (is_real(value) and above < value <= maximum):
                raise ConfigError(f"{name} must be a number > {above:g} and <= {maximum:g}, got {value!r}")
        else:
            object.__setattr__(obj, f.name, parse_choice(name, value, meta["choices"], meta["optional"]))


def _num(x: float) -> str:
    """``x`` briefly: ``1e6`` rather than ``1e+06``."""
    return f"{x:g}".replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")


def range_text(f: dataclasses.Field) -> str:
    """The allowed values of a declared setting, as the documentation states them."""
    meta = f.metadata
    kind = meta["kind"]
    if kind == "bool":
        return "true, false"
    if kind == "choice":
        return ", ".join([f"`{c.value}`" for c in meta["choices"]] + (["`none`"] if meta["optional"] else []))
    if kind == "int":
        if meta["values"] is not None:
            text = ", ".join(map(str, meta["values"]))
        elif meta["maximum"] is None:
            text = f"integer ≥ {meta['minimum']}"
        else:
            text = f"integer {meta['minimum']} … {_num(meta['maximum'])}"
        return text + (", or unset" if meta["optional"] else "")
    lo, hi = meta["minimum"], meta["maximum"]
    if meta["above"] is not None:
        text = f"({_num(meta['above'])}, {_num(hi)}]"
    elif lo is not None:
        text = f"[{_num(lo)}, {_num(hi)}]" if hi is not None else f"≥ {_num(lo)}"
    elif meta["sign"] == "positive":
        text = f"(0, {_num(hi)}]" if hi is not None else "> 0"
    elif meta["sign"] == "non-negative":
        text = f"[0, {_num(hi)}]" if hi is not None else "≥ 0"
    else:
        text = f"≤ {_num(hi)}" if hi is not None else "any"
    return text + ("" if meta["finite"] else ", inf allowed")
