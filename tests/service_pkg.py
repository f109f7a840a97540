"""A throwaway service package for launcher tests: its source written under a temporary folder that both this
process and the services the launcher starts can import."""
from __future__ import annotations

import os


def install_service_package(tmp_path, monkeypatch, package: str, source: str) -> str:
    """Write ``source`` as ``package/t.py`` under ``tmp_path``, put ``tmp_path`` on the import path of this process
    and of its children (PYTHONPATH); returns the module name to start (``package.t``)."""
    pkg = tmp_path / package
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "t.py").write_text(source)
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.syspath_prepend(str(tmp_path))
    return f"{package}.t"
