"""Files the package reads at run time besides its modules travel in a wheel only when
pyproject.toml lists them as package data."""

import fnmatch
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "src" / "ultraboneudf"
PYPROJECT = ROOT / "pyproject.toml"


def test_every_data_file_is_declared_package_data():
    declared = tomllib.loads(PYPROJECT.read_text())["tool"]["setuptools"]["package-data"]
    data = [p for p in PACKAGE.rglob("*") if p.is_file() and p.suffix not in (".py", ".pyc")
            and "__pycache__" not in p.parts]
    assert data, "no data files found: the check would prove nothing"
    for path in data:
        package = ".".join(path.parent.relative_to(PACKAGE.parent).parts)
        patterns = declared.get(package, [])
        assert any(fnmatch.fnmatch(path.name, pat) for pat in patterns), f"{path} is not in package-data"
