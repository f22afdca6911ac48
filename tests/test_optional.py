"""Optional packages: imported at first use, or an error that names the extra to install."""

from __future__ import annotations

import pytest

from service import optional
from service.optional import MissingDependency, need


def test_an_installed_package_is_returned():
    assert need("json", "a test").dumps([1]) == "[1]"


def test_a_missing_package_names_its_extra(monkeypatch):
    monkeypatch.setitem(optional.EXTRAS, "elastreg_no_such_package", "train")
    with pytest.raises(
        MissingDependency,
        match=r"training needs the 'elastreg_no_such_package' package.*"
        r"pip install 'elastreg\[train\]'",
    ):
        need("elastreg_no_such_package.sub", "training")


def test_the_optional_packages_are_not_base_dependencies():
    """The server's install (pyproject's dependencies) holds none of the extras' packages."""
    import tomllib
    from pathlib import Path

    project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
    base = " ".join(project["dependencies"]).lower()
    for package, extra in optional.EXTRAS.items():
        if package != "distributed":  # dask[distributed] names it
            assert package not in base, package
            assert any(package in r.lower() for r in project["optional-dependencies"][extra]), (package, extra)
