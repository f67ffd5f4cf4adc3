"""The one user-error type of the ``retarget`` package."""


class RetargetError(ValueError):
    """A user error in retargeting: a bad trajectory or profile, an unknown body,
    an infeasible clip. The message names the file or field and the fix; ``time_s``, where
    the error is about one moment of a clip (an infeasible one), is that moment, seconds
    into the clip as given."""

    def __init__(self, message: str, time_s: float | None = None):
        super().__init__(message)
        self.time_s = time_s
