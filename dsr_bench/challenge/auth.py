"""Team tokens: made with `secrets`, stored as argon2 hashes, checked in constant time; failed attempts slowed down.

A token reads `dsrc_<key>_<secret>`: the key (12 hex digits, not secret) finds the team's row, and the whole
token is verified against the row's argon2id hash (argon2-cffi compares in constant time). An unknown key is
verified against a dummy hash, so a wrong key and a wrong secret take the same time. `FailureThrottle` counts
failures per client address: each failure is answered after a growing delay, and past `limit` failures within
`window` seconds the address is refused (429) until the oldest failure leaves the window, whatever it sends.

Browsers: a team signs in on /login with its token once and gets a session cookie (`SessionSigner`): the team's id,
its token's key and an expiry, signed with HMAC-SHA256 under a key drawn at the server's start (a restart signs
everyone out; the token stays valid), sent HttpOnly and SameSite=Strict (Secure over HTTPS). A form that changes
something (a final choice, signing out) carries a CSRF token derived from the cookie (`csrf_token`), checked in
constant time, and a cross-site Origin is refused: another site can neither read the cookie nor post with it.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import threading
import time
from collections import deque

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError

TOKEN_PATTERN = re.compile(r"dsrc_([0-9a-f]{12})_[A-Za-z0-9_-]{43}")
#: OWASP's argon2id recommendation (19 MiB, 2 passes, 1 lane): about 20-40 ms per check on one core
_HASHER = PasswordHasher(time_cost=2, memory_cost=19 * 1024, parallelism=1)
_DUMMY_HASH = _HASHER.hash("dsrc_000000000000_" + "0" * 43)


def new_token() -> tuple[str, str]:
    """(key, token): a fresh token and the key in it."""
    key = secrets.token_hex(6)
    return key, f"dsrc_{key}_{secrets.token_urlsafe(32)}"


def token_key(token: str) -> str | None:
    """The key of a well-formed token, None for anything else."""
    match = TOKEN_PATTERN.fullmatch(token)
    return match.group(1) if match else None


def hash_token(token: str) -> str:
    """The argon2id hash (PHC string) to store for a token."""
    return _HASHER.hash(token)


def verify_token(token: str, stored_hash: str | None) -> bool:
    """Whether `token` matches `stored_hash` (None: no such team, checked against a dummy hash for equal time)."""
    try:
        return _HASHER.verify(stored_hash or _DUMMY_HASH, token) and stored_hash is not None
    except (VerificationError, InvalidHashError):
        return False


class FailureThrottle:
    """Failed authentications per client address: `delay(address)` says how long to hold the answer to a failure
    (0.1 s doubled per earlier failure, at most `max_delay`), `blocked(address)` how many seconds the address is
    refused for (0: not), after `limit` failures within `window` seconds."""

    def __init__(self, limit: int = 10, window: float = 900.0, max_delay: float = 2.0):
        self.limit, self.window, self.max_delay = limit, window, max_delay
        self._failures: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def _recent(self, address: str, now: float) -> deque[float]:
        times = self._failures.setdefault(address, deque())
        while times and times[0] <= now - self.window:
            times.popleft()
        return times

    def blocked(self, address: str) -> float:
        """Seconds until `address` may try again (0.0: it may now)."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(address, now)
            return max(0.0, times[0] + self.window - now) if len(times) >= self.limit else 0.0

    def failed(self, address: str) -> float:
        """Record a failure of `address`; returns the delay (seconds) to hold its answer."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(address, now)
            times.append(now)
            if len(self._failures) > 100_000:  # bound the memory an address scan could take
                self._failures = {a: t for a, t in self._failures.items() if t and t[-1] > now - self.window}
            return min(self.max_delay, 0.1 * 2 ** (len(times) - 1))

    def count(self, address: str) -> int:
        """Failures of `address` within the window."""
        with self._lock:
            return len(self._recent(address, time.monotonic()))


class SessionSigner:
    """Signed session cookies and their CSRF tokens (module doc), under a key drawn when it is made."""

    #: the cookie's name and lifetime (seconds)
    COOKIE, LIFETIME = "dsr_session", 12 * 3600

    def __init__(self, key: bytes | None = None):
        self._key = key or secrets.token_bytes(32)

    def _mac(self, text: str) -> str:
        return hmac.new(self._key, text.encode(), hashlib.sha256).hexdigest()

    def issue(self, team_id: int, token_key: str, now: float | None = None) -> str:
        """A cookie value for team `team_id` (its token's key `token_key`), valid for `LIFETIME` seconds."""
        body = f"{team_id}.{token_key}.{int((now or time.time()) + self.LIFETIME)}"
        return f"{body}.{self._mac(body)}"

    def read(self, value: str, now: float | None = None) -> tuple[int, str] | None:
        """(team id, token key) of a valid, unexpired cookie value, else None."""
        parts = value.split(".")
        if len(parts) != 4 or not parts[0].isdigit() or not parts[2].isdigit():
            return None
        body = ".".join(parts[:3])
        if not hmac.compare_digest(self._mac(body), parts[3]) or int(parts[2]) < (now or time.time()):
            return None
        return int(parts[0]), parts[1]

    def csrf_token(self, cookie: str) -> str:
        """The CSRF token of the forms shown to the holder of session cookie `cookie`."""
        return self._mac("csrf:" + cookie)[:32]

    def csrf_ok(self, cookie: str, token: str) -> bool:
        """Whether a form's CSRF `token` is the one of `cookie` (constant time)."""
        return hmac.compare_digest(self.csrf_token(cookie), token)
