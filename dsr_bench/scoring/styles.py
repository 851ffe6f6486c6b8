"""One colour, line style and marker per method, wherever it is drawn (the per-step plots of `dsr-bench evaluate`,
the leaderboard's figures, 3D, 2D and planning alike), and which rows are yardsticks rather than methods compared
(`is_reference_method`: the leaderboard's tables and the challenge's too). Names are matched loosely
(`method_key`): "DSR-Net", "dsr-cpu" and "dsr-cpu (planning)" are one method.
"""

from __future__ import annotations

import hashlib
import re

#: One colour, line style and marker per method, wherever it is drawn (3D, 2D, planning, evaluate's plot):
#: keyed by `method_key`. Reference rows are dashed, dotted or dash-dotted; trained rows solid. "no push"
#: (planning's do-nothing) shares static's look: both are "no motion".
METHOD_STYLES: dict[str, tuple[str, str, str]] = {
    "static": ("#4d4d4d", "--", "o"),
    "nopush": ("#4d4d4d", "--", "o"),
    "push": ("#8c564b", ":", "^"),
    "oracle": ("#000000", "-.", "*"),
    "random": ("#bcbd22", ":", "v"),
    "dsr": ("#1f77b4", "-", "o"),
    "single": ("#ff7f0e", "-", "s"),
    "nowarp": ("#2ca02c", "-", "D"),
    "gtwarp": ("#d62728", "-", "P"),
    "3dflow": ("#9467bd", "-", "X"),
    "2dflow": ("#e377c2", "-", "p"),
    "se3net": ("#17becf", "-", "h"),
    "se3posenet": ("#5254a3", "-", "d"),
}
#: colours for methods the map does not name, picked by a hash of the name (the same colour in every figure)
OTHER_COLOURS = ("#393b79", "#637939", "#8c6d31", "#843c39", "#7b4173", "#3182bd", "#e6550d", "#31a354",
                 "#756bb1", "#636363", "#9c9ede", "#cedb9c")
_ALIASES = {"dsrnet": "dsr", "singlestep": "single", "nomotion": "static"}
#: rows that are yardsticks, not methods being compared: drawn as references, never "best"
REFERENCE_KEYS = ("static", "nopush", "push", "oracle", "random")


def method_key(method: str) -> str:
    """The key of a method in `METHOD_STYLES`: lower case, a parenthesised note, a "-cpu"/"-gpu" track suffix,
    a " ft" (finetuned) suffix and punctuation dropped, paper names mapped ("DSR-Net" -> "dsr"); e.g.
    "dsr-cpu", "DSR-Net" and "dsr-cpu (planning)" are all "dsr"."""
    name = re.sub(r"\s*\([^)]*\)", "", str(method).lower()).strip()
    name = re.sub(r"[-_ ](cpu|gpu)$", "", re.sub(r"\s+ft$", "", name))
    name = re.sub(r"[^a-z0-9]", "", name)
    return _ALIASES.get(name, name)


def method_style(method: str) -> dict:
    """Matplotlib keywords (color, linestyle, marker) of a method, the same in every figure."""
    key = method_key(method)
    if key in METHOD_STYLES:
        colour, line, marker = METHOD_STYLES[key]
    else:
        digest = int(hashlib.sha256(key.encode()).hexdigest(), 16)
        colour, line, marker = OTHER_COLOURS[digest % len(OTHER_COLOURS)], "-", "o"
    return {"color": colour, "linestyle": line, "marker": marker}


def is_reference_method(method: str) -> bool:
    """Whether a row is a yardstick (static, push, oracle, random, no push) rather than a method compared."""
    key = method_key(method)
    return key in REFERENCE_KEYS or "oracle" in str(method).lower()


def is_oracle(method: str) -> bool:
    """Whether a row is an oracle (drawn apart: it would squeeze the other rows' axis)."""
    return "oracle" in str(method).lower()
