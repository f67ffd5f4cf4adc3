"""The real-time control loop and what it is built from: the fixed-rate clock and real-time
settings, the target buffer and its interpolation, the playback clock, the safety filter and
the loop itself (``control.loop.ControlLoop``). Importing this package imports nothing else."""
