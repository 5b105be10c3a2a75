"""The errors a user can fix.

Every error this package raises for a user's input (a file, a parameter, a probe sample, an
artifact) derives from :class:`PmaskError`; the ``pmask`` command prints such an error as one line
that says what is wrong and what to change.  Anything else that escapes is a bug in pmask, and the
command shows its traceback with a request to report it.  The subclasses also derive from the
built-in exception a Python caller would expect (``ValueError``, ``OSError``), so ``except
ValueError`` keeps working.
"""


class PmaskError(Exception):
    """An error the user can fix; its message says what to change."""


class InputError(PmaskError, ValueError):
    """A parameter, value or file content that cannot be used."""


class ResourceError(PmaskError, MemoryError):
    """A job that does not fit this machine (memory, disk) or its time budget."""


class OutputError(PmaskError, OSError):
    """An output that cannot be written (folder, permissions, full disk)."""
