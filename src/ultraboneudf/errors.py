"""The one exception type for bad user input, and the warning for tolerated input defects.

The CLI turns an :class:`InputError` into a single line on stderr and exit code 2; anything else
is a bug and exits with 1. A :class:`SweepWarning` is printed as one line after a successful run.
"""


class InputError(ValueError):
    """Bad user input. The message names the file or value and says what is wrong with it."""


class FitWarning(UserWarning):
    """The mesh does not fit its input (``Reconstruction.fit_warnings``): input points far from the
    mesh, or mesh area far from every input point."""


class SweepWarning(UserWarning):
    """A tolerated defect of a sweep file (duplicated key, skipped INVALID frame, …)."""
