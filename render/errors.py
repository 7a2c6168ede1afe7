"""The one exception type for user errors (bad input, bad options, failed stages).

The CLI turns a `SineError` into one readable line and a non-zero exit, without a traceback.
Everything else is a bug and keeps its traceback.
"""


class SineError(Exception):
    """A problem the user can fix: the message says what is wrong and what to do."""
