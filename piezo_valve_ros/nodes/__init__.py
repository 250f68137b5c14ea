"""The ROS 2 nodes, one module each: ``hardware``, ``controller``, ``composed`` (both in one process),
``identification`` and ``monitor``; ``common`` is their shared ROS plumbing.  Thin shells over the core."""
