"""Errors that the command line reports as a one-line message (no traceback)."""


class EndowaveError(Exception):
    """Bad input or state the user can fix; the message names the file and the problem."""


class DataError(EndowaveError):
    """A scene on disk is missing, malformed or inconsistent."""
