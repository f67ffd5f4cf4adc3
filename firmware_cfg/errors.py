"""The one user-error type of the ``firmware_cfg`` package."""


class ConfigError(ValueError):
    """A bad hardware config or servo table entry; the message names the file and field."""
