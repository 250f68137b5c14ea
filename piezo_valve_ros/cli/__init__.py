"""The command-line tools, one module each, named by what follows ``valve_``: ``identify``, ``tune``, ``plot``,
``record``, ``command`` and ``rig``; ``tool`` is what they share (how they end, the time window).  Thin faces over
the library (``piezo_valve_ros.identify``, ``rig``, ``io``, the core); no node imports from here."""
