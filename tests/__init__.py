"""The test suite of flatserve (a package, so that ``tests.harness`` imports
from the repository root)."""
