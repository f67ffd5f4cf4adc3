"""The one user-error type of the ``dualflow`` package."""


class DualFlowError(ValueError):
    """A user error in ``dualflow``: a bad motion file, a wrong shape, a bad config.

    The message names the file or field, what is wrong and how to fix it, so the
    command line can print it in one line. Bugs raise other exception types.
    """
