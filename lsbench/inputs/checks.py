"""What an input value may be, written once and said in words.

A `Rule` checks a value read from a scenario file (TOML types, strictly: "3" is not 3, true is
not 1, 32.5 is not an integer) or parses the text of a command-line flag. A bad value becomes one
line that names the key or flag, shows the value and says what is allowed, e.g.
`[run] repeats = "3" (a string) is not an integer >= 1` or
`argument --rel-tol: nan is not a finite number >= 0`. The scenario loader
(inputs/scenario.py) and the flags (commands/common.py) use the same rules, so a setting allows
the same values in both places.
"""
from __future__ import annotations

import argparse
import difflib
import json
import math
import numbers
import re
import tempfile
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

# Most rays one image may have: 2^26 = 8192x8192. primary_rays builds them through float64
# temporaries of about 80 bytes a ray (5 GiB here); a typo such as 100000x100000 (10^10 rays)
# would otherwise end in a numpy MemoryError traceback instead of a sentence.
MAX_IMAGE_RAYS = 2**26


class BadValue(ValueError):
    """One input value that is not allowed; the message names it, shows it and says what is."""


def show(value: Any) -> str:
    """A value as the user wrote it in TOML (strings quoted, true/false, lists, tables)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(show(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {show(v)}" for k, v in value.items()) + " }"
    return repr(value)


_TYPE_WORDS = {bool: "a boolean", str: "a string", int: "an integer", float: "a number",
               list: "a list", dict: "a table"}


def show_typed(value: Any) -> str:
    """`show`, plus the TOML type when it may be the mistake: "3" (a string)."""
    word = _TYPE_WORDS.get(type(value))
    return f"{show(value)} ({word})" if isinstance(value, (bool, str)) else show(value)


def did_you_mean(word: str, known: Iterable[str]) -> str:
    """' (did you mean "x"?)' for a near miss among `known`, else ''."""
    known = list(known)
    lowered = {k.lower(): k for k in known}
    close = difflib.get_close_matches(str(word).lower(), list(lowered), n=1, cutoff=0.6)
    return f" (did you mean {show(lowered[close[0]])}?)" if close else ""


@dataclass(frozen=True)
class Rule:
    """What one setting allows: a test on a value of its TOML type, and the same in words."""
    allowed: str  # completes "VALUE is not ...", e.g. "an integer >= 1"
    accepts: Callable[[Any], bool]
    from_text: Callable[[str], Any] = str  # a flag's text -> the value (ValueError if it is none)
    names: tuple[str, ...] = ()  # for a choice of names: suggested on a near miss
    noun: str = ""  # what a name names ("structure"): an unknown one is said so, like a key

    def check(self, name: str, value: Any) -> Any:
        """The value, or BadValue naming `name` (a key such as "[run] width")."""
        if not self.accepts(value):
            if self.noun and isinstance(value, str):
                raise BadValue(f"{name} = {show(value)} is an unknown {self.noun}"
                               f"{did_you_mean(value, self.names)}; allowed: {self.allowed}")
            raise BadValue(f"{name} = {show_typed(value)} is not {self.allowed}")
        return value

    def flag(self, text: str) -> Any:
        """argparse `type=`: the value, or ArgumentTypeError (argparse names the flag)."""
        try:
            value = self.from_text(text)
        except ValueError:
            value = None  # accepted by no rule
        if value is None or not self.accepts(value):
            raise argparse.ArgumentTypeError(f"{text} is not {self.allowed}")
        return value


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)  # TOML true is a bool, not 1


def _is_finite(v) -> bool:
    # numbers.Real: numpy scalars too, for cameras built in code
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def integer(low: int) -> Rule:
    return Rule(f"an integer >= {low}", lambda v: _is_int(v) and v >= low, int)


def number(low: float, high: float | None = None, low_open: bool = False,
           high_open: bool = False) -> Rule:
    """A finite number >= low (> low when low_open), <= high (< high when high_open)."""
    if high is None:
        text = f"a finite number {'>' if low_open else '>='} {low:g}"
    else:
        text = f"a number in {'(' if low_open else '['}{low:g}, {high:g}{')' if high_open else ']'}"

    def accepts(v) -> bool:
        return (_is_finite(v) and (v > low if low_open else v >= low)
                and (high is None or (v < high if high_open else v <= high)))
    return Rule(text, accepts, float)


def one_of(names: Iterable[str], noun: str) -> Rule:
    names = tuple(names)
    return Rule("one of " + ", ".join(show(n) for n in names),
                lambda v: isinstance(v, str) and v in names, str, names, noun)


def leaf_size_rule() -> Rule:
    """bvh / bvh-ls leaf_size: 0 (the structure's default) or one of the sizes the build takes
    (backends/structures/bvh.py: LEAF_SIZES)."""
    from lsbench.backends.structures.bvh import LEAF_SIZES

    allowed = (0,) + tuple(LEAF_SIZES)
    return Rule("0 (the structure's default) or one of " + ", ".join(map(str, LEAF_SIZES)),
                lambda v: _is_int(v) and v in allowed, int)


FLAG = Rule("true or false", lambda v: isinstance(v, bool))
TEXT = Rule("a non-empty string", lambda v: isinstance(v, str) and v != "")
POINT = Rule("3 finite numbers [x, y, z]",
             lambda v: isinstance(v, list) and len(v) == 3 and all(_is_finite(x) for x in v))
# A pinhole camera's vertical field of view: tan(fov/2) is 0 at 0 degrees and infinite at 180.
FOV = number(0, 180, low_open=True, high_open=True)

_RESOLUTION_TEXT = re.compile(r"[1-9][0-9]*(x[1-9][0-9]*x[1-9][0-9]*)?", re.IGNORECASE)
RESOLUTION = Rule('a positive integer or "RxRyRz" (64 or "64x32x16")',
                  lambda v: (_is_int(v) and v >= 1)
                  or (isinstance(v, str) and _RESOLUTION_TEXT.fullmatch(v) is not None))


# A setting the model picks (lsbench/model/cost.py, docs/fit.md): resolution, ls_n and
# ls_min_candidates may be "auto", chosen per case under the device-memory budget (budget_mib).
AUTO = "auto"


def or_auto(rule: Rule) -> Rule:
    """`rule`'s values, or "auto"."""
    return Rule(f'{rule.allowed}, or "auto" (chosen by the cost model under the budget)',
                lambda v: v == AUTO or rule.accepts(v),
                lambda text: AUTO if text.strip().lower() == AUTO else rule.from_text(text))


RESOLUTION_OR_AUTO = or_auto(RESOLUTION)
# The device-memory budget of a case's structure (budget_mib, --budget), in MiB.
BUDGET = number(0, low_open=True)


def check_list(name: str, value: Any, item: Rule) -> list:
    """A key that takes one value or a non-empty list of them ("backends", "ls_n", ...)."""
    if not isinstance(value, list):
        if item.accepts(value):
            return [value]
        raise BadValue(f"{name} = {show_typed(value)} is not {item.allowed}, or a non-empty list of them")
    if not value:
        raise BadValue(f"{name} = [] is empty: it needs {item.allowed}, or a non-empty list of them")
    for i, v in enumerate(value):
        item.check(f"{name}[{i}]", v)
    return value


def check_keys(where: str, table: dict, known: Iterable[str]) -> None:
    """No key outside `known`: a typo (`backend =` for `backends =`) would otherwise be ignored
    and the default used in its place."""
    known = list(known)
    for key in table:
        if key not in known:
            raise BadValue(f"{where}unknown key {show(key)}{did_you_mean(key, known)}; "
                           f"allowed: {', '.join(known)}")


def check_image_size(width: int, height: int) -> None:
    if width * height > MAX_IMAGE_RAYS:
        raise BadValue(f"{width}x{height} is {width * height} rays, over the limit of "
                       f"{MAX_IMAGE_RAYS} (2^26, e.g. 8192x8192) rays per image")


def check_camera(prefix: str, eye, target, up, fov) -> None:
    """The values a pinhole camera needs (inputs/rays.primary_rays): three points of 3 finite
    numbers, eye and target apart, a field of view in (0, 180) degrees. `prefix` goes before
    each key's name in the message ("camera." in a scenario)."""
    for key, point in (("eye", eye), ("target", target), ("up", up)):
        as_list = list(point) if isinstance(point, tuple) or hasattr(point, "tolist") else point
        POINT.check(f"{prefix}{key}", as_list)
    FOV.check(f"{prefix}fov", fov)
    if list(map(float, eye)) == list(map(float, target)):
        raise BadValue(f"{prefix}eye = {show(list(eye))} is not allowed: it equals target "
                       "(a camera looks from eye towards target)")


def writable_folder(text: str) -> str:
    """argparse `type=` for an output folder: one that exists and lsbench can write files in,
    or one that can be created (checked by creating and removing a file where it would go, so
    read-only file systems and permissions count as they will, even for root). Nothing stays
    behind; the command creates the folder when it needs it."""
    path = Path(text)
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        what = "is" if existing == path else f"cannot be created: {existing} is"
        raise argparse.ArgumentTypeError(f"{text} {what} a file; allowed: a folder that exists or "
                                         "can be created, and is writable")
    try:
        with tempfile.TemporaryFile(dir=existing):
            pass
    except OSError as exc:
        raise argparse.ArgumentTypeError(
            f"{text} is not writable ({exc.strerror or exc} in {existing}); allowed: a folder that "
            "exists or can be created, and is writable") from None
    return text


# ---- Ray-set parameters ------------------------------------------------------------------------
# What each generated ray set (inputs/rays.py, inputs/secondary.py) takes, with its default: a
# scenario's `ray_params = { ... }` ([run] or [[cases]]) and `--ray-param KEY=VALUE` are checked
# against these rules, and a case carries its parameters with the defaults filled in (a default
# of None is derived from the scene: the shadow rays' light). A ray set not listed takes none.
SEED = integer(0)
RAY_PARAMS: dict[str, dict[str, tuple[Rule, Any]]] = {
    "shadow": {"light": (POINT, None), "light_size": (number(0), 0.0), "samples": (integer(1), 1),
               "seed": (SEED, 0)},
    "ao": {"samples": (integer(1), 4), "distance": (number(0, low_open=True), 0.1), "seed": (SEED, 0)},
    "diffuse": {"seed": (SEED, 0)},
    "incoherent": {"count": (integer(1), None), "seed": (SEED, 0)},
}


def resolve_ray_params(where: str, rays: str, params: Any) -> tuple:
    """The parameters of ray set `rays` as a case holds them: `params` (a table) checked key by
    key against RAY_PARAMS, the defaults filled in, sorted (key, value) pairs with lists as
    tuples (a case is hashable). `where` names the table in messages ("[run] ")."""
    if not isinstance(params, dict):
        raise BadValue(f"{where}ray_params = {show_typed(params)} is not a table "
                       "{ key = value, ... }")
    rules = RAY_PARAMS.get(rays, {})
    if params and not rules:
        raise BadValue(f"{where}ray_params = {show(params)}: the ray set {show(rays)} takes no "
                       f"parameters (those that do: {', '.join(sorted(RAY_PARAMS))})")
    check_keys(f"{where}ray_params for {show(rays)}: ", params, rules)
    resolved = {}
    for key, (rule, default) in rules.items():
        value = rule.check(f"{where}ray_params.{key}", params[key]) if key in params else default
        if value is not None:
            resolved[key] = tuple(value) if isinstance(value, list) else value
    return tuple(sorted(resolved.items()))


def ray_param_text(text: str) -> tuple[str, Any]:
    """argparse `type=` for --ray-param KEY=VALUE: VALUE in TOML syntax (4, 0.25, [0, 5, 0]),
    as the same key in a scenario's ray_params table would be written."""
    import tomllib

    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key or not value.strip():
        raise argparse.ArgumentTypeError(f"{text} is not KEY=VALUE (e.g. samples=4)")
    try:
        return key, tomllib.loads(f"v = {value}")["v"]
    except tomllib.TOMLDecodeError:
        raise argparse.ArgumentTypeError(f"{text}: {value} is not a TOML value "
                                         "(a number, or a list such as [0, 5, 0])") from None
