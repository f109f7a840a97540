"""Recordings of the bus as MCAP files: ``writer`` (MCAP files with rotation by size and time), ``foxglove`` (the
project's messages as Foxglove-known channels), ``recorder`` (a service: bus -> MCAP), ``replayer`` (a service:
MCAP -> bus) and ``golden`` (the committed regression recording). docs/recording.md describes the files."""
