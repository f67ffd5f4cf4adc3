"""Telemetry of a run: the crash-safe per-tick log (``telemetry.log``: writer, reader, the
record format) and its plots (``telemetry.plots``, matplotlib). Importing this package imports
neither."""
