"""Method names as a reader sees them: the leaderboard never shows a name that reads like a reference row's, or
like another entry's, without being it.

`fold(name)`: the name as it reads: Unicode NFKC (full-width and mathematical letters, ligatures, NBSP and the other
spaces as plain ones), accents and invisible characters dropped (zero-width spaces and joiners, bidi controls, soft
hyphens, variation selectors, Hangul fillers), letters of other scripts that look like Latin ones mapped to them
(`CONFUSABLES`: Cyrillic, Greek, Armenian and Latin look-alikes, a small explicit part of Unicode's confusables,
UTS #39), case folded, runs of whitespace one space. `skeleton(name)`: its letters and digits alone (spaces and
punctuation dropped): two names with one skeleton are confusable. `reference_claim(name)`: the reference row a name
reads as (`REFERENCE_NAMES`), by its skeleton or by the key the tables and figures style a method by
(`dsr_bench.scoring.styles.method_key`: "Static (mine)", "static-cpu" and "No motion" read as static).
`name_problem(name)`: why a name cannot be shown at all (bidi controls, which reorder what is shown; no letter or
digit), or None.
"""

from __future__ import annotations

import unicodedata
from collections.abc import Iterable

from dsr_bench.scoring.styles import method_key

#: every reference row's name, in both tracks: the predictions' yardsticks (`dsr-bench predict --model static`,
#: push, oracle) and the planning track's (random, and no push: the tasks' start states)
REFERENCE_NAMES = ("static", "push", "oracle", "random", "no push")

#: bidirectional controls (marks, embeddings, overrides, isolates): they reorder the characters shown around them
BIDI_CONTROLS = frozenset("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")
#: invisible characters outside Unicode's format category (Cf, dropped too): combining grapheme joiner, Hangul
#: fillers, Mongolian vowel separator, variation selectors
_INVISIBLE = frozenset("\u034f\u115f\u1160\u3164\uffa0\u180e" + "".join(map(chr, range(0xFE00, 0xFE10))))

#: look-alikes of Latin letters -> the Latin letter (applied before and after case folding)
CONFUSABLES = str.maketrans({
    # Cyrillic
    "\u0430": "a", "\u0435": "e", "\u043e": "o", "\u0440": "p", "\u0441": "c", "\u0443": "y", "\u0445": "x",
    "\u0455": "s", "\u0456": "i", "\u0458": "j", "\u04bb": "h", "\u0501": "d", "\u051b": "q", "\u051d": "w",
    "\u04cf": "l", "\u0410": "A", "\u0412": "B", "\u0415": "E", "\u041a": "K", "\u041c": "M", "\u041d": "H",
    "\u041e": "O", "\u0420": "P", "\u0421": "C", "\u0422": "T", "\u0423": "Y", "\u0425": "X", "\u0405": "S",
    "\u0406": "I", "\u0408": "J", "\u051a": "Q", "\u051c": "W", "\u04c0": "l", "\u04ae": "Y", "\u04af": "y",
    # Greek
    "\u03b1": "a", "\u03bf": "o", "\u03c1": "p", "\u03b9": "i", "\u03ba": "k", "\u03bd": "v", "\u03c5": "u",
    "\u03c7": "x", "\u03b3": "y", "\u03f2": "c", "\u03f3": "j", "\u0391": "A", "\u0392": "B", "\u0395": "E",
    "\u0396": "Z", "\u0397": "H", "\u0399": "I", "\u039a": "K", "\u039c": "M", "\u039d": "N", "\u039f": "O",
    "\u03a1": "P", "\u03a4": "T", "\u03a5": "Y", "\u03a7": "X", "\u03f9": "C", "\u037f": "J",
    # Armenian
    "\u0585": "o", "\u057d": "u", "\u0570": "h", "\u0578": "n", "\u0566": "q", "\u0581": "g",
    # Latin letters that read as others
    "\u0131": "i", "\u0237": "j", "\u0251": "a", "\u0261": "g", "\u0269": "i", "\u01c0": "l",
})


def _invisible(c: str) -> bool:
    return unicodedata.category(c) == "Cf" or c in _INVISIBLE


def fold(name: str) -> str:
    """A name as it reads (module doc): NFKC, accents and invisible characters dropped, look-alikes mapped to Latin
    letters, case folded, whitespace runs one space."""
    text = unicodedata.normalize("NFKD", unicodedata.normalize("NFKC", str(name)))
    text = "".join(c for c in text if not _invisible(c) and unicodedata.category(c) not in ("Mn", "Me"))
    text = text.translate(CONFUSABLES).casefold().translate(CONFUSABLES)
    return " ".join(unicodedata.normalize("NFC", text).split())


def skeleton(name: str) -> str:
    """The letters and digits of `fold(name)`: two names with the same skeleton are confusable."""
    return "".join(c for c in fold(name) if c.isalnum())


_REFERENCE_SKELETONS = {skeleton(n): n for n in REFERENCE_NAMES}
_REFERENCE_KEYS = {method_key(n): n for n in REFERENCE_NAMES}


def reference_claim(name: str) -> str | None:
    """The reference row (`REFERENCE_NAMES`) that `name` reads as, or None."""
    return _REFERENCE_SKELETONS.get(skeleton(name)) or _REFERENCE_KEYS.get(method_key(fold(name)))


def name_problem(name: str) -> str | None:
    """Why a method's name cannot be shown, as a phrase, or None."""
    bidi = next((c for c in str(name) if c in BIDI_CONTROLS), None)
    if bidi is not None:
        return (f"method {ascii(str(name)[:60])} holds the bidi control U+{ord(bidi):04X}, which reorders what is "
                "shown; remove it (meta.json's name)")
    if not skeleton(name):
        return f"method {ascii(str(name)[:60])} shows no letter or digit; give it a name (meta.json's name)"
    return None


def confusable_with(name: str, others: Iterable[str]) -> str | None:
    """The first of `others` that reads like `name` (the same skeleton) without being the same string, or None."""
    key = skeleton(name)
    return next((o for o in others if o != name and skeleton(o) == key), None)
