"""The live partner pipeline: actor frames in, robot targets out, off the control loop's thread.

``reactor`` (DualFlow, the only torch user here), ``retarget_stage``, ``core`` (both stages
and the real-time policy), ``pipeline`` (the thread that feeds the loop), ``idle_slots``
(when catch-up work runs), ``process`` / ``child`` / ``wire`` (the same core in a child
process). How they fit together: docs/partner_pipeline.md. Importing this package imports
nothing else (no torch).
"""
