"""The error family that the command line reports as one line (no traceback), and nothing else.

Everything a user can cause and fix (a bad file, a bad option, a folder in the wrong state) is a
:class:`KpcnError` whose message names the file, the layer or the option and what was found. Any other
exception is a bug and keeps its traceback.
"""


class KpcnError(Exception):
    """Bad input or state that a user can fix; the message names the file, layer or option."""


class OptionError(KpcnError, ValueError):
    """An option (a config field) out of range: ``str()`` is ``"<option> <detail>"``. The command line
    names the option by its flag instead (``val_fraction`` -> ``--val-fraction``)."""

    def __init__(self, option: str, detail: str):
        super().__init__(f"{option} {detail}")
        self.option = option
        self.detail = detail

    def __reduce__(self):  # raised in a worker process, it is pickled back to the caller
        return type(self), (self.option, self.detail)


class InputFileError(KpcnError, ValueError):
    """A file a scene reads (an image texture, an environment map) that cannot be read or holds no usable
    image; the message starts with the file's path."""


class ArrayError(KpcnError, ValueError):
    """An array handed to ``kpcn.denoise`` that it cannot take (not numbers, complex, of a wrong shape); the
    message names the argument and what it was."""
