"""JSON files the toolkit did not write (a submitted results file, a leaderboard entry, a planning run's
results.json): `read_json` returns the value whatever the file holds, or raises `UnreadableJSON` saying why in a few
words, never another exception of the parser's (a file that is not UTF-8, malformed, holding an integer longer
than Python converts or nested deeper than the recursion limit)."""

from __future__ import annotations

import json
import sys
from pathlib import Path


class UnreadableJSON(ValueError):
    """A file that does not hold JSON this toolkit can read; the message says why, in a few words."""


def read_json(path: str | Path):
    """The JSON value of an untrusted file, or `UnreadableJSON` (module doc)."""
    try:
        return json.loads(Path(path).read_bytes().decode("utf-8"))
    except OSError as exc:
        raise UnreadableJSON(f"cannot be read: {exc.strerror or type(exc).__name__}") from None
    except UnicodeDecodeError:
        raise UnreadableJSON("not UTF-8 text") from None
    except json.JSONDecodeError as exc:
        raise UnreadableJSON(f"not valid JSON: line {exc.lineno}, column {exc.colno}, {exc.msg}") from None
    except ValueError as exc:  # an integer of more digits than int() converts
        limit = getattr(sys, "get_int_max_str_digits", lambda: 4300)()
        raise UnreadableJSON(f"an integer of more than {limit} digits" if "digits" in str(exc) else
                             f"not JSON this toolkit reads: {' '.join(str(exc).split())[:60]}") from None
    except RecursionError:
        raise UnreadableJSON("JSON nested deeper than this toolkit reads") from None
