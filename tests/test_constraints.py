"""constraints.txt pins every dependency the project installs, within pyproject.toml's
ranges, and this suite runs on exactly those versions: what CI tests is what the
image ships (docker/Dockerfile and the Makefile install with ``-c constraints.txt``)."""
from __future__ import annotations

import re
from importlib import metadata
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parent.parent
PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==(\S+)\s*$")


def pins() -> dict[str, str]:
    out = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        m = PIN.match(line)
        assert m, f"constraints.txt: not a pin: {line!r}"
        out[canonicalize_name(m.group(1))] = m.group(2)
    return out


def requirements() -> list[Requirement]:
    """Every requirement of pyproject.toml: core, each extra, the build system."""
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    project = doc["project"]
    reqs = list(project["dependencies"]) + doc["build-system"]["requires"]
    for extra in project["optional-dependencies"].values():
        reqs += extra
    return [Requirement(r) for r in reqs]


def test_every_requirement_is_pinned_within_its_range():
    pinned = pins()
    for req in requirements():
        name = canonicalize_name(req.name)
        assert name in pinned, f"{req.name} is not in constraints.txt: run make constraints"
        assert req.specifier.contains(Version(pinned[name]), prereleases=True), \
            f"{req.name}=={pinned[name]} is outside pyproject.toml's {req.specifier}"


def test_the_suite_runs_on_the_pinned_versions():
    wrong = {}
    for name, version in pins().items():
        try:
            have = metadata.version(name)
        except metadata.PackageNotFoundError:
            wrong[name] = (None, version)
            continue
        if Version(have) != Version(version):
            wrong[name] = (have, version)
    assert not wrong, f"installed vs pinned (make test installs the pins): {wrong}"
