"""What the hardware is: config schema, servo model tables, protocol specs and
provisioning. Depends on nothing else of this project."""

from firmware_cfg.errors import ConfigError

__all__ = ["ConfigError"]
