"""The ``measured`` role: a number on a page, read from a generated file at build time.

    {measured}`bench:runtime.kidney_1543.load.warm.load_s|.2f` s

``SOURCE:PATH|FORMAT``: SOURCE names a file (:data:`SOURCES`, written by ``make bench``), or ``ref/NAME`` a stored
reference table (``tests/reference/NAME.csv``, recomputed by CI and by ``make reference``; its rows as a list),
PATH is a dotted path into its JSON (list indices as numbers; a key with dots of its own, ``kidney_0.003``, as it
is; ``a[key=value]`` picks the first element of a list whose ``key`` equals ``value``), FORMAT a Python format
spec (``,`` for thousands, ``.2f``, ``.1e``...; ``%`` multiplies by 100), after ``GiB`` or ``MiB`` for a number
of bytes shown in that unit (``GiB.2f``), after ``min`` for seconds shown in minutes (``min.0f``).
A path that does not resolve is an error, so a page cannot quote a number its generated file no longer has:
every measured number in the docs comes from a generated file.
"""
from __future__ import annotations

import csv
import json
import re
from pathlib import Path

from docutils import nodes

ROOT = Path(__file__).resolve().parents[2]
#: source name -> the generated file it reads
SOURCES = {
    "bench": ROOT / "bench" / "results.json",
    "compress": ROOT / "bench" / "compress_results.json",
    "amg": ROOT / "bench" / "amg_verdict.json",  # a record: the AMG route's last runs, before it was removed
    "figures": ROOT / "docs" / "figures.json",   # the figures' own numbers, written by `make figures`
}
_cache: dict = {}
#: units a FORMAT may start with: bytes, seconds
UNITS = {"GiB": 2**30, "MiB": 2**20, "min": 60}


def _load(name: str):
    if name not in _cache:
        if name.startswith("ref/"):
            lines = (ROOT / "tests" / "reference" / f"{name[4:]}.csv").read_text().splitlines()
            rows = list(csv.DictReader(line for line in lines if not line.startswith("# ")))
            _cache[name] = [{k: _number(v) for k, v in r.items()} for r in rows]
        else:
            _cache[name] = json.loads(SOURCES[name].read_text())
    return _cache[name]


def _number(v: str):
    try:
        return float(v)
    except ValueError:
        return v


_PICK = re.compile(r"^(?P<key>[^\[]*)\[(?P<field>[^=\]]+)=(?P<value>[^\]]*)\]$")


def lookup(spec: str):
    """The value ``SOURCE:PATH`` names (KeyError/IndexError/ValueError when it does not resolve)."""
    source, _, path = spec.partition(":")
    value = _load(source)
    parts = path.split(".")
    while parts:
        part = parts.pop(0)
        if isinstance(value, dict) and part not in value:  # a key with dots of its own (``kidney_0.003``)
            k = next((k for k in range(len(parts), 0, -1) if ".".join([part, *parts[:k]]) in value), 0)
            part, parts = ".".join([part, *parts[:k]]), parts[k:]
        m = _PICK.match(part)
        if m:
            if m["key"]:
                value = value[m["key"]]
            value = next(v for v in value if str(v.get(m["field"])) == m["value"])
        elif isinstance(value, list):
            value = value[int(part)]
        else:
            value = value[part]
    return value


def render(spec: str) -> str:
    where, _, fmt = spec.partition("|")
    value = lookup(where.strip())
    if isinstance(value, str) or not fmt:
        return str(value)
    for unit, size in UNITS.items():
        if fmt.startswith(unit):
            value, fmt = value / size, fmt[len(unit):]
    return format(value, fmt)


def measured_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    try:
        out = render(text)
    except (KeyError, IndexError, ValueError, StopIteration, TypeError, FileNotFoundError) as exc:
        msg = inliner.reporter.error(f"measured: {text!r} does not resolve in its generated file ({exc!r})",
                                     line=lineno)
        return [inliner.problematic(rawtext, rawtext, msg)], [msg]
    return [nodes.inline(rawtext, out, classes=["measured"])], []


def setup(app):
    app.add_role("measured", measured_role)
    for path in SOURCES.values():
        app.connect("env-get-outdated", lambda app, env, added, changed, removed, p=path: [])
    return {"version": "1.0", "parallel_read_safe": True, "parallel_write_safe": True}
