"""The typed reader of scene-file tables, shared by every table the scene parser validates.

`Table` wraps one TOML table: each accessor (`number`, `integer`, `string`, `boolean`, `vector`)
reads one key with its type, default and allowed range, and `done()` reports keys nobody read, in
the manner of pbrt-v4's ParameterDictionary (`GetOneFloat`, `ReportUnused`). Every failure is one
`InputError` naming the file, the table and the key, and saying what is allowed.

Representable values. The renderer computes in float32 (largest finite value 3.4e38), so a value
that is finite as a Python float can still overflow: 1e39 is inf in float32, and a coordinate of
1e20 squared (a distance², a dot product) is. Every number read here is therefore also bounded by
`MAX_MAGNITUDE` = 1e18 in absolute value, unless the caller asks for a tighter range: a square of
such a value (1e36), and sums of a few of them, stay finite in float32, and so do radiometric
products such as intensity / distance² at ordinary distances. `check_vec3`, `check_rgb` and
`check_range` (the validated value updates of `jaxrt.scene.Scene`) apply the same bound, and
`jaxrt.scene.build` applies it to vertices after their transforms and to environment-map texels
after their scale.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from jaxrt.errors import InputError

#: The largest magnitude of any scene number (coordinates, lengths, radiometric values, uv
#: transforms): squares and sums of a few squares of it stay finite in float32 (see above).
MAX_MAGNITUDE = 1e18


#: The thin lens (jaxrt.camera): a focus distance of at least MIN_FOCUS_DISTANCE keeps the ray
#: directions' squares normal float32 numbers, and an aperture of at most MAX_APERTURE_RATIO times
#: the focus distance keeps hit distances (up to the lens radius) precise at the scale of the focus
#: distance; beyond it float32 rays lose the scene and the image turns black.
MIN_FOCUS_DISTANCE = 1e-12
MAX_APERTURE_RATIO = 1e3


def _finite(x) -> bool:
    """x is an int or float (not a bool) that is finite as a float (huge ints are not)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return False
    try:
        return math.isfinite(x)
    except OverflowError:
        return False


def printable(name) -> str:
    """A key or table name as shown in a message: itself, or its repr when it holds control
    characters (a quoted TOML key may contain a newline; messages stay one line)."""
    name = str(name)
    return name if name.isprintable() else repr(name)


def _bounds(lo, hi):
    return max(lo, -MAX_MAGNITUDE), min(hi, MAX_MAGNITUDE)


def check_range(v, lo, hi, where):
    lo, hi = _bounds(lo, hi)
    try:
        x = float(v)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected a number in [{lo:g}, {hi:g}], got {v!r}") from None
    if not (lo <= x <= hi):
        raise InputError(f"{where}: {x:g} is outside the allowed range [{lo:g}, {hi:g}]")
    return x


def _array(v, where, what):
    try:
        return np.asarray(v, np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{where}: expected {what}, got {v!r}") from None


def check_vec3(v, where):
    """3 finite numbers of magnitude <= MAX_MAGNITUDE, as float32."""
    a = _array(v, where, "3 finite numbers")
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{where}: expected 3 finite numbers, got {v!r}")
    if np.any(np.abs(a) > MAX_MAGNITUDE):
        raise InputError(f"{where}: {v!r}: every component must be in [{-MAX_MAGNITUDE:g}, {MAX_MAGNITUDE:g}]")
    return a.astype(np.float32)


def check_rgb(v, where, lo=0.0):
    """One number or an RGB triple in [lo, MAX_MAGNITUDE], as a float32 triple."""
    a = _array(v, where, f"a finite number or RGB triple >= {lo:g}")
    if a.shape == ():
        a = np.full(3, float(a))
    if a.shape != (3,) or not np.all(np.isfinite(a)) or np.any(a < lo):
        raise InputError(f"{where}: expected a finite number or RGB triple >= {lo:g}, got {v!r}")
    if np.any(a > MAX_MAGNITUDE):
        raise InputError(f"{where}: {v!r}: every component must be in [{lo:g}, {MAX_MAGNITUDE:g}]")
    return a.astype(np.float32)


_REQ = object()



class Table:
    """Typed access to one TOML table with error messages naming file, table and key."""

    def __init__(self, file: str, table: str, data: Any):
        self.file, self.table = file, printable(table)
        if not isinstance(data, dict):
            self.fail(None, f"expected a table, got {type(data).__name__}")
        self.data = data
        self.used: set[str] = set()

    def fail(self, key, msg):
        where = f"{self.file}: [{self.table}]" + (f" {printable(key)}" if key else "")
        raise InputError(f"{where}: {msg}")

    def raw(self, key, default=_REQ):
        self.used.add(key)
        if key not in self.data:
            if default is _REQ:
                self.fail(key, "is required but missing")
            return default
        return self.data[key]

    def number(self, key, default=_REQ, lo=-math.inf, hi=math.inf, lo_open=False, hi_open=False):
        """A number in the range (bounded by ±MAX_MAGNITUDE where the range is wider)."""
        v = self.raw(key, default)
        if v is None:
            return None
        if not _finite(v):
            self.fail(key, f"expected a finite number, got {v!r}")
        if lo < -MAX_MAGNITUDE:
            lo, lo_open = -MAX_MAGNITUDE, False
        if hi > MAX_MAGNITUDE:
            hi, hi_open = MAX_MAGNITUDE, False
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
        """n numbers, each in [lo, MAX_MAGNITUDE] (lo at least -MAX_MAGNITUDE)."""
        v = self.raw(key, default)
        if v is None:
            return None
        if scalar_ok and isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v] * n
        ok = (
            isinstance(v, list)
            and len(v) == n
            and all(_finite(x) for x in v)
        )
        if not ok:
            alt = " or a single number" if scalar_ok else ""
            self.fail(key, f"expected a list of {n} finite numbers{alt}, got {v!r}")
        if any(x < lo for x in v):
            self.fail(key, f"{v!r}: every component must be >= {lo:g}")
        lo, hi = _bounds(lo, math.inf)
        if any(not lo <= x <= hi for x in v):
            self.fail(key, f"{v!r}: every component must be in [{lo:g}, {hi:g}]")
        return tuple(float(x) for x in v)

    def done(self, extra_allowed: Sequence[str] = ()):
        unknown = [k for k in self.data if k not in self.used and k not in extra_allowed]
        if unknown:
            allowed = sorted(self.used | set(extra_allowed))
            self.fail(unknown[0], f"unknown key; allowed: {', '.join(allowed)}")



class Names:
    """The object names of one namespace (a scene's objects and instances, or one group's objects).

    An explicit name must be unique: a second use is an error naming both tables (a silent rename
    would make `--object NAME` pick the wrong object). A default name (an unnamed object's
    primitive or mesh stem, an unnamed instance's GROUP.K) gets .2, .3, ... when it is taken or is
    some table's explicit name.
    """

    def __init__(self, reserved=()):
        self.reserved = set(reserved)
        self.taken: dict[str, str] = {}  # name -> the table that holds it, as messages show it

    @classmethod
    def of(cls, doc: Any) -> "Names":
        """The namespace of a document's [[objects]] and [[instances]], with their explicit names reserved."""
        reserved = []
        for key in ("objects", "instances"):
            tables = doc.get(key) if isinstance(doc, dict) else None
            for t in tables if isinstance(tables, list) else ():
                if isinstance(t, dict) and isinstance(t.get("name"), str):
                    reserved.append(t["name"])
        return cls(reserved)

    def claim(self, name: str, table: "Table") -> str:
        if name in self.taken:
            table.fail("name", f"{name!r} is already the name of {self.taken[name]}; names must be unique")
        self.taken[name] = f"[{table.table}]"
        return name

    def generate(self, base: str, table: "Table") -> str:
        name, k = base, 2
        while name in self.taken or name in self.reserved:
            name, k = f"{base}.{k}", k + 1
        self.taken[name] = f"[{table.table}]"
        return name



def parse_transform(c: "Table") -> tuple:
    """(scale, rotate, translate) of an object or instance table, each None when absent."""
    scale = c.raw("scale", None)
    if scale is not None:
        scale = c.vector("scale", 3, lo=1e-30, scalar_ok=True)
        if any(s <= 0 for s in scale):
            c.fail("scale", "every component must be > 0")
    return scale, c.vector("rotate", 3, default=None), c.vector("translate", 3, default=None)
