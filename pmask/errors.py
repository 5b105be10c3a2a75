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

    def __reduce__(self):
        # pickled as its own class with its message, so that one raised on a Dask worker reaches the client as
        # itself (one line): distributed's tblib otherwise rebuilds a ResourceError through MemoryError.__new__,
        # which refuses it, and the client gets a bare Exception with a traceback
        return type(self), self.args, self.__dict__ or None


class InputError(PmaskError, ValueError):
    """A parameter, value or file content that cannot be used."""


class ResourceError(PmaskError, MemoryError):
    """A job that does not fit this machine (memory, disk) or its time budget."""


class OutputError(PmaskError, OSError):
    """An output that cannot be written (folder, permissions, full disk)."""
