"""eonav services: one module per process, each a thin wrapper around the pure library in ``eonav/``
built on the node skeleton ``eonav.bus.node``. Run one with ``python -m eonav.services.<name>`` or
``eonav service <name>``; run them all with ``eonav run``."""
