"""Errors a user can trigger by bad input.

Every such error carries one line that names the file, the name or the value
and says what would be valid; the CLI prints it and exits with status 2.
"""


class MjstampError(ValueError):
    """Bad input: a one-line message naming the culprit and the valid choices."""


def valid_list(names, limit: int = 40) -> str:
    """Formats valid choices for an error message: 'a, b, c' (truncated)."""
    names = [str(n) for n in names]
    if not names:
        return "(none)"
    if len(names) > limit:
        return ", ".join(names[:limit]) + f", ... ({len(names) - limit} more)"
    return ", ".join(names)


class FidelityWarning(UserWarning):
    """The gradient model parts from the physics plans are verified in (one line).

    The solve goes on: every plan is verified, and repaired, in MuJoCo C.
    """
