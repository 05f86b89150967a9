"""configs/ ships with the wheel: runtime/configs links to it and pyproject.toml's package data
covers every file in it (tests/deploy/test_wheel.py then runs the installed wheel)."""

from __future__ import annotations

import fnmatch
import tomllib

from machine_files import ROOT

from runtime.config import SHIPPED_CONFIGS_DIR

PACKAGE_DATA = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
    "package-data"
]


def test_the_package_data_directory_is_the_repositorys_configs() -> None:
    link = ROOT / "runtime" / "configs"
    assert link.is_symlink() and str(link.readlink()) == "../configs"
    assert SHIPPED_CONFIGS_DIR == ROOT / "configs"


def test_every_file_of_configs_ships_as_package_data() -> None:
    for path in (ROOT / "configs").rglob("*"):
        if path.is_dir():
            continue
        package = ".".join(("runtime", "configs", *path.parent.relative_to(ROOT / "configs").parts))
        patterns = PACKAGE_DATA.get(package, [])
        assert any(fnmatch.fnmatch(path.name, pattern) for pattern in patterns), (
            f"{path.relative_to(ROOT)} matches no package-data pattern of {package} "
            "in pyproject.toml"
        )
