"""The softmotion version, written in this one place.

``pyproject.toml`` reads :data:`VERSION` when a wheel is built (``[tool.setuptools.dynamic]``);
``softmotion --version``, the Modbus identity registers and ``softmotion doctor`` import it.
"""

VERSION = "0.1.0"


def version_numbers(version: str = VERSION) -> tuple[int, int, int]:
    """(major, minor, patch) of ``version``; a part that is not a plain number reads 0."""
    parts = [int(part) if part.isdigit() else 0 for part in version.split(".")[:3]]
    major, minor, patch = parts + [0] * (3 - len(parts))
    return major, minor, patch
