"""The installed package holds every module: ``pip install .`` (a wheel, not the editable install the
README uses) once left out ``logtools.latency`` because pyproject listed the packages by hand."""
from __future__ import annotations

import tomllib
from pathlib import Path

from setuptools import find_packages

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_of_the_repository_goes_into_the_wheel():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "packages" not in cfg or isinstance(cfg["packages"], dict), "packages listed by hand"
    include = cfg["packages"]["find"]["include"]
    found = set(find_packages(str(ROOT), include=include))
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for top in ("logtools", "parsers", "pipelines", "tapost")
               for p in (ROOT / top).rglob("__init__.py")}
    assert on_disk and on_disk <= found, sorted(on_disk - found)
    assert "logtools.latency" in found
    data = cfg["package-data"]["pipelines"]
    assert any((ROOT / "pipelines").glob(g) for g in data)  # report_schema.json ships with the code
