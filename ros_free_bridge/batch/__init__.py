"""The offline batch behind ``dualflow-bridge retarget-check``: many clips retargeted and checked in physics.

Modules, each depending only on those before it: ``clips`` (which clips), ``config`` (the settings),
``results`` (rows, the result log, the tables), ``clip_check`` (one clip), ``report_html`` (the pages),
``local`` and ``ray_engine`` (the engines), ``run`` (:func:`run_batch`). Importing this package
imports none of them. Reference: docs/retarget_check.md.
"""
