"""pyproject.toml lists every package and ships every file of configs/: the wheel holds what a
checkout has (tests/deploy/test_wheel.py then runs it)."""

from __future__ import annotations

import fnmatch
import tomllib

from machine_files import ROOT

SETUPTOOLS = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def test_every_python_package_is_listed() -> None:
    on_disk = {
        ".".join(init.parent.relative_to(ROOT).parts)
        for top in ("planner", "drives", "runtime")
        for init in (ROOT / top).rglob("__init__.py")
    }
    listed = {name for name in SETUPTOOLS["packages"] if not name.startswith("runtime.configs")}
    assert listed == on_disk, "pyproject.toml [tool.setuptools] packages must list every package"


def test_every_file_of_configs_ships_as_package_data() -> None:
    package_dir = SETUPTOOLS["package-dir"]["runtime.configs"]
    assert (ROOT / package_dir).is_dir()
    for path in (ROOT / package_dir).rglob("*"):
        if path.is_dir():
            continue
        relative = path.parent.relative_to(ROOT / package_dir).parts
        package = ".".join(("runtime.configs", *relative))
        assert package in SETUPTOOLS["packages"], f"{package} (for {path.name}) is not listed"
        patterns = SETUPTOOLS["package-data"].get(package, [])
        assert any(fnmatch.fnmatch(path.name, pattern) for pattern in patterns), (
            f"{path.relative_to(ROOT)} matches no package-data pattern of {package}"
        )
