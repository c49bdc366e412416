"""Config errors: :class:`ConfigError` (a ``ValueError``, one line per problem) and the
formatting of pydantic's errors as ``<dotted.path[index]>: <what is wrong> (got <value>)``."""

from __future__ import annotations

import re

from pydantic import ValidationError


class ConfigError(ValueError):
    """A bad experiment file; ``lines`` holds one message per problem."""

    def __init__(self, lines: list[str]):
        self.lines = list(lines)
        super().__init__("\n".join(self.lines))


def _loc(loc) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out or "<root>"


def _under(loc: tuple, line: str) -> str:
    """A problem line relative to a model (``b: ...``, ``[2]: ...``, ``<root>: ...``) placed
    under the model's own path ``loc``."""
    head = _loc(loc)
    if line.startswith("<root>"):
        return head + line[len("<root>"):]
    return line if head == "<root>" else head + ("" if line.startswith("[") else ".") + line


def _short(v) -> str:
    s = repr(v)
    return s if len(s) <= 80 else s[:77] + "..."


_UNION_TAG = re.compile(r"^(constrained-|literal\[|function-|nullable|union\[|json-or-python|(int|float|str|bool)$|(list|dict|tuple)\[)")


def _format(err: ValidationError, prefix: tuple = ()) -> list[str]:
    """One line per bad key; a value that fails every branch of a union (``chunk: 0`` against
    ``int >= 1 | 'auto'``) is one line with the branches' messages joined by "or"."""
    lines: list[str] = []
    merged: dict[tuple, int] = {}  # (loc, input) of a union's first branch -> its line
    for e in err.errors(include_url=False):
        loc = prefix + tuple(x for x in e["loc"] if not (isinstance(x, str) and _UNION_TAG.match(x)))
        union = len(loc) != len(prefix) + len(e["loc"])
        msg = e["msg"]
        if e["type"] == "value_error":
            msg = msg.removeprefix("Value error, ")
        if e["type"] == "value_error" and isinstance((e.get("ctx") or {}).get("error"), ConfigError):
            lines += [_under(loc, x) for x in e["ctx"]["error"].lines]  # a model's checks, one line each (jskel.checks)
        elif e["type"] == "missing":
            lines.append(f"{_loc(loc)}: required key is missing")
        elif e["type"] == "extra_forbidden":
            lines.append(f"{_loc(loc)}: unknown key (got {_short(e['input'])})")
        elif union and (loc, _short(e["input"])) in merged:
            i = merged[(loc, _short(e["input"]))]
            lines[i] = lines[i].replace(" (got ", f", or {msg[0].lower() + msg[1:]} (got ", 1)
        else:
            if union:
                merged[(loc, _short(e["input"]))] = len(lines)
            lines.append(f"{_loc(loc)}: {msg} (got {_short(e['input'])})")
    return lines
