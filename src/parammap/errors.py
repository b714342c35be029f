"""The one error type for bad input.

Every error a user can cause with a file, a setting or an argument derives from
:class:`InputError`; the command line prints it in one line and exits with 2. Anything
else is a bug and keeps its traceback.
"""

from __future__ import annotations

__all__ = ["InputError"]


class InputError(ValueError):
    """Bad input: a capture file, a photo, a setting or an argument (the message names
    it). A ``ValueError``, so callers that caught those still do."""
