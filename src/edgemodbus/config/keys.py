"""Keys of a config section: their spellings, unknown keys and misspelt ones.

A key matches a field in any spelling (case, ``_`` and ``-`` ignored: compat.py's
:func:`~edgemodbus.config.compat.norm_key`).  A key that matches no field is

* an error when it looks like a misspelling of one of the section's keys
  (:func:`misspelt`: ``"dataMultipler"`` would otherwise leave an item unscaled,
  ``"hots"`` connect MQTT to the default host): ``did you mean dataMultiplier?``;
* else a warning (the seed's files carry UI keys: ``label``, ``orderNo``...), logged
  once the load is over, a bounded number of lines and then one summary line
  (:func:`log_unknown`), the key quoted and cut (:func:`quote_key`): a file is
  untrusted text.
"""

from __future__ import annotations

import difflib
import logging
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

from .compat import norm_key
from .problems import NO_VALUE, ConfigError, Problem, join_path

logger = logging.getLogger("edgemodbus.config")

UNKNOWN_KEY_LINES = 20
"""Unknown-key warnings logged (or told in an error) per load; the rest are counted in
one summary line."""

KEY_SHOWN = 40
"""Characters of an unknown key shown in a message (a key may be megabytes long)."""

UI_KEYS: frozenset[str] = frozenset(norm_key(k) for k in (
    # the seed descriptor's and its UI's keys (tests/data/seed-descriptor.json): files
    # exported from that UI carry them beside the fields
    "label", "orderNo", "controlType", "category", "type", "defaultValue", "options",
    "value", "visibleWhen", "note", "min", "max", "parameter", "dataSource",
    "addressExamples", "addressParameter", "addressRegex", "allowManualAddress",
    "hasBuiltInAddresses", "protocolCategory", "supportedDataTypes",
    "supportsDynamicBrowse", "supportsPresets", "coil", "discreteInput",
    "holdingRegister", "inputRegister", "id", "remark", "remarks", "comment", "tags",
    # what tag lists and OPC-style exports carry beside a tag
    "quality", "timestamp", "group", "access", "readOnly", "writable", "precision",
    "alias", "notes", "enabled",
))
"""Keys real files carry that are no field of ours: never taken for a misspelling."""


def quote_key(key: Any) -> str:
    """An untrusted key as a message shows it: repr, cut to :data:`KEY_SHOWN` chars."""
    text = repr(key[: KEY_SHOWN + 1] if isinstance(key, str) else key)
    if len(text) > KEY_SHOWN + 2:
        text = text[:KEY_SHOWN] + "...'"
    return text


def _path_key(key: str) -> str:
    """A key in a path: as written if it is a plain word, else quoted and cut."""
    plain = key.replace("_", "").replace("-", "")
    return key if plain.isascii() and plain.isalnum() and len(key) <= KEY_SHOWN \
        else quote_key(key)


# --------------------------------------------------------------------------- misspellings


def distance(a: str, b: str, limit: int) -> int:
    """Damerau-Levenshtein distance of ``a`` and ``b`` (optimal string alignment:
    insertions, deletions, substitutions and swaps of neighbours cost 1), or
    ``limit + 1`` as soon as it is known to be more than ``limit``."""
    if abs(len(a) - len(b)) > limit:
        return limit + 1
    before: list[int] = []
    prev = list(range(len(b) + 1))
    for i in range(1, len(a) + 1):
        row = [i] + [0] * len(b)
        for j in range(1, len(b) + 1):
            cost = a[i - 1] != b[j - 1]
            row[j] = min(prev[j] + 1, row[j - 1] + 1, prev[j - 1] + cost)
            if i > 1 and j > 1 and a[i - 1] == b[j - 2] and a[i - 2] == b[j - 1]:
                row[j] = min(row[j], before[j - 2] + 1)
        if min(row) > limit:
            return limit + 1
        before, prev = prev, row
    return min(prev[len(b)], limit + 1)


def allowed_distance(known: str) -> int:
    """How far a key may be from ``known`` (normalised) to be taken for its misspelling:
    1 for keys of 3 to 7 characters (``hots`` -> ``host``), 2 for longer ones
    (``datamultpler`` -> ``datamultiplier``), none for shorter ones.  Two edits in a
    short key would make many words typos of one another (``unit`` and ``type``,
    ``metrics`` and ``retries``)."""
    return 0 if len(known) < 3 else 1 if len(known) <= 7 else 2


def _deletions(word: str, most: int) -> set[str]:
    """``word`` with up to ``most`` characters deleted."""
    found = {word}
    edge = {word}
    for _ in range(most):
        edge = {w[:i] + w[i + 1:] for w in edge for i in range(len(w))}
        found |= edge
    return found


_MOST = 2  # the largest allowed_distance


class _Index:
    """The keys of one section, indexed for :func:`misspelt` by their deletion variants
    (symmetric deletion: two strings within k edits, a swap of neighbours included,
    share a string both reach by deleting at most k characters), so that an unknown
    key is compared with the few keys it may misspell, not with every key."""

    __slots__ = ("canonical", "longest", "variants")

    def __init__(self, table: Mapping[str, str]) -> None:
        self.canonical = dict(table)
        self.longest = max(map(len, table), default=0)
        self.variants: dict[str, set[str]] = {}
        for known in table:
            for variant in _deletions(known, allowed_distance(known)):
                self.variants.setdefault(variant, set()).add(known)

    def candidates(self, norm: str) -> set[str]:
        found: set[str] = set()
        for variant in _deletions(norm, _MOST):
            found |= self.variants.get(variant, set())
        return found


_indexes: dict[int, tuple[Mapping[str, str], _Index]] = {}


def misspelt(table: Mapping[str, str], key: str, exempt: frozenset[str]) -> str | None:
    """The key of ``table`` (normalised -> canonical) that ``key`` misspells, or None:
    the closest within :func:`allowed_distance` (Damerau-Levenshtein, after
    normalisation, so a case-only difference is no key of ours at all), unless ``key``
    is one of ``exempt`` (a UI key, or a key of another section)."""
    norm = norm_key(key)
    if norm in exempt or len(norm) < 3:
        return None
    cached = _indexes.get(id(table))
    if cached is None or cached[0] is not table:
        cached = (table, _Index(table))
        _indexes[id(table)] = cached
    index = cached[1]
    if len(norm) > index.longest + _MOST:
        return None  # far longer than any key (a 10 MB key is not cut into variants)
    best: tuple[int, str] | None = None
    for known in sorted(index.candidates(norm)):
        limit = allowed_distance(known)
        found = distance(norm, known, limit)
        if found <= limit and (best is None or found < best[0]):
            best = (found, known)
    return None if best is None else index.canonical[best[1]]


# --------------------------------------------------------------------------- normalising


def normalize(table: Mapping[str, str], data: Mapping[Any, Any], where: str, prefix: str,
              exempt: Callable[[], frozenset[str]]) -> dict[str, Any]:
    """``data`` with canonical keys.  A key given twice in different spellings, or a
    misspelt one, is a ConfigError (paths from ``prefix``); other unknown keys are
    told (:func:`unknown_key`, ``where`` names the place) and dropped.  ``exempt()``:
    the keys never taken for misspellings (asked only when a key is unknown)."""
    out: dict[str, Any] = {}
    spelled: dict[str, str] = {}
    problems: list[Problem] = []
    for key, value in data.items():
        canon = table.get(norm_key(key)) if isinstance(key, str) else None
        if canon is None:
            meant = misspelt(table, key, exempt()) if isinstance(key, str) else None
            if meant is None:
                unknown_key(where, key)
            else:
                problems.append(Problem(join_path(prefix, _path_key(key)), NO_VALUE,
                                        f"unknown key: did you mean {meant}? (a misspelt "
                                        "key would be ignored)"))
            continue
        if canon in out:
            problems.append(
                Problem(
                    join_path(prefix, canon), value, f"given twice (also as {spelled[canon]!r})"
                )
            )
            continue
        out[canon] = value
        spelled[canon] = key
    if problems:
        raise ConfigError(problems)
    return out


# --------------------------------------------------------------------------- unknown keys


# Unknown keys met while a load is under way (None: log them at once, see collecting)
_unknown_keys: ContextVar[list[Problem] | None] = ContextVar("edgemodbus_unknown_keys",
                                                             default=None)


def unknown_key(where: str, key: Any) -> None:
    """Tell an unknown key: kept for the load under way, else logged at once."""
    problem = Problem(where, NO_VALUE, f"unknown key {quote_key(key)} ignored")
    sink = _unknown_keys.get()
    if sink is None:
        logger.warning("%s", problem)
    else:
        sink.append(problem)


def unknown_count() -> int | None:
    """Unknown keys met so far by the load under way (None: no load collects them)."""
    sink = _unknown_keys.get()
    return None if sink is None else len(sink)


@contextmanager
def collecting() -> Iterator[list[Problem]]:
    """Collect the unknown keys met inside (instead of logging each at once)."""
    unknown: list[Problem] = []
    token = _unknown_keys.set(unknown)
    try:
        yield unknown
    finally:
        _unknown_keys.reset(token)


def bounded(unknown: Sequence[Problem]) -> list[Problem]:
    """The first :data:`UNKNOWN_KEY_LINES` unknown keys and, if there are more, one line
    counting the rest (200,000 unknown keys are 21 lines, not 17 MB of warnings)."""
    shown = list(unknown[:UNKNOWN_KEY_LINES])
    rest = len(unknown) - len(shown)
    if rest > 0:
        shown.append(Problem("...", NO_VALUE,
                             f"and {rest:,} more unknown key{'s' if rest > 1 else ''} "
                             "ignored"))
    return shown


def log_unknown(unknown: Sequence[Problem]) -> None:
    """Log the unknown keys of a load that succeeded, bounded (:func:`bounded`)."""
    for problem in bounded(unknown):
        logger.warning("%s", problem)


def with_unknown_keys(error: ConfigError, unknown: Sequence[Problem]) -> ConfigError:
    """The error's problems plus the unknown keys (bounded): a key that looks like a
    misspelling of a field the error says is missing joins that line; the others get a
    line each."""
    problems = list(error.problems)
    rest: list[Problem] = []
    for extra in unknown:
        key = extra.message.removeprefix("unknown key ").removesuffix(" ignored")
        for i, problem in enumerate(problems):
            parent, _, field = problem.path.rpartition(".")
            if (
                problem.value is NO_VALUE
                and parent == extra.path
                and difflib.get_close_matches(norm_key(key.strip("'\"")), [norm_key(field)],
                                              cutoff=0.5)
            ):
                problems[i] = Problem(problem.path, NO_VALUE,
                                      f"{problem.message} (the unknown key {key} was ignored)")
                break
        else:
            rest.append(extra)
    return ConfigError(problems + bounded(rest))


__all__ = ["KEY_SHOWN", "UI_KEYS", "UNKNOWN_KEY_LINES", "allowed_distance", "bounded",
           "collecting", "distance", "log_unknown", "misspelt", "normalize", "quote_key",
           "unknown_key", "with_unknown_keys"]
