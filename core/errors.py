"""User-facing errors: anything the user can fix (bad path, corrupt file, bad parameter).

The CLI prints ``str(error)`` as one line on stderr and exits non-zero; no traceback.
Messages name the file (or parameter) first, then the problem.
"""


class LidarlocError(Exception):
    """A problem with the user's input or configuration, reported as one line."""


class DataError(LidarlocError):
    """A data file is missing, corrupt or inconsistent."""
