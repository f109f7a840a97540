"""The applications: the ``eonav`` command line, the launcher of the whole pipeline, the demo, benchmarks, pictures.

The top layer: it may import every other one; nothing imports it but the entry point.
"""
