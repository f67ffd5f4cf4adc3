"""``python -m ros_free_bridge`` is the same as the ``dualflow-bridge`` command."""

from ros_free_bridge.cli import main

raise SystemExit(main())
