"""How the suite runs: on two workers (pytest-xdist, ``-n 2`` in pyproject.toml), with the tests that hold fixed
resources in one serial group, and the numba kernels compiled once before the workers start.

- ``sitl`` tests start autopilots on fixed ports (one SITL instance number each), ``netns`` tests make network
  namespaces of fixed names, and ``pipeline`` tests run the whole pipeline against its real-time budgets (two at
  once on two cores drop frames as too old, as the services should): they run one after another on one worker
  (``xdist_group``, ``--dist loadgroup``) while the other worker takes the rest.
- A fresh install compiles the dense method's and the fusion's kernels (tens of seconds of CPU); numba caches them
  on disk. Compiled here by the controller, the workers and every service process they start only load them, instead
  of two workers compiling the same kernels at once inside whichever tests come first.
"""
import pytest

SERIAL_MARKERS = ("sitl", "netns", "pipeline")


def pytest_configure(config):
    workers = getattr(config.option, "numprocesses", None)
    if hasattr(config, "workerinput") or not workers or config.option.collectonly:
        return                  # a worker (the controller compiled them), a serial run, or collection only
    from eonav.fusion.sequence import prepare_kernels
    prepare_kernels()


def pytest_collection_modifyitems(config, items):
    for item in items:
        if any(item.get_closest_marker(m) for m in SERIAL_MARKERS):
            item.add_marker(pytest.mark.xdist_group("fixed-resources"))
