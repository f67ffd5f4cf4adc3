"""One module per subcommand; see :mod:`ros_free_bridge.cli`."""
