#!/usr/bin/env python3
"""Print the requirements of pyproject.toml, one a line, for `pip install -r`.

    python3 scripts/requirements.py [--no-core] [EXTRA ...]

The core dependencies and those of each named extra (deduplicated, in order).
Used where the dependencies are installed before the package itself: the
Makefile's test extra (no rebuild of the package) and the container image (a
layer that depends on pyproject.toml only).
"""
from __future__ import annotations

import sys
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib


def requirements(pyproject: Path, extras: list[str], core: bool = True) -> list[str]:
    project = tomllib.loads(pyproject.read_text())["project"]
    optional = project.get("optional-dependencies", {})
    out = list(project.get("dependencies", [])) if core else []
    for extra in extras:
        if extra not in optional:
            raise SystemExit(f"no extra {extra!r} in {pyproject} (have: {', '.join(optional)})")
        out += optional[extra]
    return list(dict.fromkeys(out))


def main(argv: list[str]) -> int:
    core = "--no-core" not in argv
    extras = [a for a in argv if a != "--no-core"]
    pyproject = Path(__file__).resolve().parent.parent / "pyproject.toml"
    if not pyproject.is_file():  # copied on its own (the container build)
        pyproject = Path("pyproject.toml")
    print("\n".join(requirements(pyproject, extras, core)))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
