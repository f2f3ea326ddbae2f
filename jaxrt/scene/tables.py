"""The typed reader of scene-file tables, shared by every table the scene parser validates.

`Table` wraps one TOML table: each accessor (`number`, `integer`, `string`, `boolean`, `vector`)
reads one key with its type, default and allowed range, and `done()` reports keys nobody read, in
the manner of pbrt-v4's ParameterDictionary (`GetOneFloat`, `ReportUnused`). Every failure is one
`InputError` naming the file, the table and the key, and saying what is allowed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from jaxrt.errors import InputError


def check_range(v, lo, hi, where):
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected a number in [{lo:g}, {hi:g}], got {v!r}") from None
    if not (lo <= x <= hi):
        raise InputError(f"{where}: {x:g} is outside the allowed range [{lo:g}, {hi:g}]")
    return x



def check_vec3(v, where):
    a = np.asarray(v, np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{where}: expected 3 finite numbers, got {v!r}")
    return a.astype(np.float32)



def check_rgb(v, where, lo=0.0):
    a = np.asarray(v, np.float64)
    if a.shape == ():
        a = np.full(3, float(a))
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(a < lo):
        raise InputError(f"{where}: expected a finite number or RGB triple >= {lo:g}, got {v!r}")
    return a.astype(np.float32)



_REQ = object()



class Table:
    """Typed access to one TOML table with error messages naming file, table and key."""

    def __init__(self, file: str, table: str, data: Any):
        self.file, self.table = file, table
        if not isinstance(data, dict):
            self.fail(None, f"expected a table, got {type(data).__name__}")
        self.data = data
        self.used: set[str] = set()

    def fail(self, key, msg):
        where = f"{self.file}: [{self.table}]" + (f" {key}" if key else "")
        raise InputError(f"{where}: {msg}")

    def raw(self, key, default=_REQ):
        self.used.add(key)
        if key not in self.data:
            if default is _REQ:
                self.fail(key, "is required but missing")
            return default
        return self.data[key]

    def number(self, key, default=_REQ, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False):
        v = self.raw(key, default)
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(key, f"expected a finite number, got {v!r}")
        if v < lo or v > hi or (lo_open and v == lo) or (hi_open and v == hi):
            rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
            self.fail(key, f"{v!r} is outside the allowed range {rng}")
        return float(v)

    def integer(self, key, default=_REQ, lo=-(2**31), hi=2**31 - 1):
        v = self.raw(key, default)
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(key, f"expected an integer, got {v!r}")
        if not lo <= v <= hi:
            self.fail(key, f"{v} is outside the allowed range [{lo}, {hi}]")
        return int(v)

    def string(self, key, default=_REQ, choices: Sequence[str] | None = None):
        v = self.raw(key, default)
        if v is None:
            return None
        if not isinstance(v, str):
            self.fail(key, f"expected a string, got {v!r}")
        if choices is not None and v not in choices:
            self.fail(key, f"{v!r} is not allowed; allowed: {', '.join(choices)}")
        return v

    def boolean(self, key, default=_REQ):
        v = self.raw(key, default)
        if not isinstance(v, bool):
            self.fail(key, f"expected true or false, got {v!r}")
        return v

    def vector(self, key, n, default=_REQ, lo=-math.inf, scalar_ok=False):
        v = self.raw(key, default)
        if v is None:
            return None
        if scalar_ok and isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v] * n
        ok = (
            isinstance(v, list)
            and len(v) == n
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
        )
        if not ok:
            alt = " or a single number" if scalar_ok else ""
            self.fail(key, f"expected a list of {n} finite numbers{alt}, got {v!r}")
        if any(x < lo for x in v):
            self.fail(key, f"{v!r}: every component must be >= {lo:g}")
        return tuple(float(x) for x in v)

    def done(self, extra_allowed: Sequence[str] = ()):
        unknown = [k for k in self.data if k not in self.used and k not in extra_allowed]
        if unknown:
            allowed = sorted(self.used | set(extra_allowed))
            self.fail(unknown[0], f"unknown key; allowed: {', '.join(allowed)}")



def unique_name(name: str, names_seen: set[str]) -> str:
    """`name`, or name.2, name.3, ... if taken; the result is added to `names_seen`."""
    base_name, k = name, 2
    while name in names_seen:
        name, k = f"{base_name}.{k}", k + 1
    names_seen.add(name)
    return name



def parse_transform(c: "Table") -> tuple:
    """(scale, rotate, translate) of an object or instance table, each None when absent."""
    scale = c.raw("scale", None)
    if scale is not None:
        scale = c.vector("scale", 3, lo=1e-30, scalar_ok=True)
        if any(s <= 0 for s in scale):
            c.fail("scale", "every component must be > 0")
    return scale, c.vector("rotate", 3, default=None), c.vector("translate", 3, default=None)
