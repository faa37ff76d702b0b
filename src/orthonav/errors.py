"""One error type for every input the user can get wrong.

The CLI turns an :class:`OrthonavError` into a one-line message naming the file or field
and what was expected; anything else is a bug and keeps its traceback.
"""


class OrthonavError(ValueError):
    """Bad input (file, field or parameter), with a message a user can act on."""
