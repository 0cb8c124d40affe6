"""The drive core: what runs a car's parts, tick after tick, from the plan ``Vehicle.add()`` makes to the report.

* :mod:`.plan` decides, once at ``add()``, how each part is called (inline, awaited, offloaded, threaded), with
  :mod:`.origin_sources` (which input an output came from);
* :mod:`.drive` is one run (:class:`~asyncdonkey.core.drive.Drive`): its lifecycle (start, the safety
  attachment, the ticks, stop, shutdown, the report), with :mod:`.partrun` (a part's state for one run),
  :mod:`.pipeline` (pipelined and reacting parts), :mod:`.profiler` (the tick table), :mod:`.drive_report`,
  :mod:`.shutdown` (two phases, actuators first) and :mod:`.signals` (Ctrl-C and SIGTERM);
* :mod:`.runtypes` holds the small Protocols the safety package and the signals are typed against, so that
  they never import the Drive class; :mod:`.buildscope` tracks what a car's ``build()`` opened.

The core imports the foundation (:mod:`asyncdonkey.clock`, :mod:`asyncdonkey.memory`,
:mod:`asyncdonkey.contracts`, :mod:`asyncdonkey.errors`, :mod:`asyncdonkey.ratelimit`) and
:mod:`asyncdonkey.safety`; never a part, a driver or a command (docs/architecture.md). This ``__init__`` imports
nothing, so importing one module of the core loads only what that module needs.
"""
