"""The one exception type that reaches users as a one-line message instead of a traceback."""


class LightstageError(Exception):
    """Bad input or a failed stage: the message names the file or field and the problem."""
