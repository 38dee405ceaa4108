"""One exception family for the whole core.

Every message names the file (or item) and the problem, so that the command line
prints it unchanged and a Blender operator can show it with
``self.report({'ERROR'}, str(err))``.
"""


class SSMError(Exception):
    """Base class of every error the SSM Builder core raises on purpose."""


class InputError(SSMError, ValueError):
    """Bad input: a missing or malformed file, an unknown label, a bad parameter value."""


class Cancelled(SSMError):
    """The user cancelled a long operation (``cancelled()`` returned True)."""


def check_cancelled(cancelled):
    """Raise :class:`Cancelled` if the optional ``cancelled()`` callable says so."""
    if cancelled is not None and cancelled():
        raise Cancelled("cancelled by the user")
