"""Errors a user can cause. The CLI prints them as one line and exits non-zero."""


class UserError(Exception):
    """A bad input from the user: the message names the input and the fix."""


def one_line(exc: BaseException) -> str:
    """The message of a UserError as one line. A UserError raised in a DataLoader worker process
    comes back re-raised with the worker's whole traceback in its message: keep the original."""
    text = str(exc)
    if text.startswith("Caught ") and "Original Traceback" in text:
        last = [line for line in text.splitlines() if line.strip()][-1]
        prefix = f"{type(exc).__module__}.{type(exc).__name__}: "
        text = last[len(prefix):] if last.startswith(prefix) else last
    return " ".join(text.split("\n"))
