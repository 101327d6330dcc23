"""The one exception type for bad user input.

The CLI turns an :class:`InputError` into a single line on stderr and exit code 2; anything else
is a bug and exits with 1.
"""


class InputError(ValueError):
    """Bad user input. The message names the file or value and says what is wrong with it."""
