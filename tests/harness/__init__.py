"""Test scaffolding (not shipped in the ``flatserve`` package): real server
processes and throwaway PostgreSQL clusters for the tests and the benchmarks.

* :mod:`tests.harness.process`: :class:`~tests.harness.process.ServerProcess`
  (``python -m flatserve.service`` in a child process on a free port) and
  :func:`~tests.harness.process.free_port`;
* :mod:`tests.harness.pgcluster`: :class:`~tests.harness.pgcluster.PgCluster`
  (``initdb`` + ``pg_ctl`` of Debian's binaries on a temporary directory, never
  the machine's own cluster).

The tests import it as ``tests.harness`` (``tests`` is a package, so pytest
puts the repository root on ``sys.path``); the benchmarks, run as scripts from
the repository root, put the root there through ``benchmarks/timing.py``.
"""
