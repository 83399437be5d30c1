"""The one error family that the command line reports as a message (no traceback)."""


class KpcnError(Exception):
    """Bad input or state that a user can fix; the message names the file, layer or option."""
