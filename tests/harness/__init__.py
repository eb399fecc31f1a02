"""Test scaffolding (not shipped in the ``flatserve`` package): real server
processes and throwaway PostgreSQL clusters for the tests and the benchmarks.

* :mod:`tests.harness.process`: :class:`~tests.harness.process.ServerProcess`
  (``python -m flatserve.service`` in a child process on a free port) and
  :func:`~tests.harness.process.free_port`;
* :mod:`tests.harness.pgcluster`: :class:`~tests.harness.pgcluster.PgCluster`
  (``initdb`` + ``pg_ctl`` of Debian's binaries on a temporary directory, never
  the machine's own cluster);
* :mod:`tests.harness.raycluster`: a Ray cluster of several nodes on loopback;
* :mod:`tests.harness.browser`: a server in a thread and headless Chromium;
* :mod:`tests.harness.fields`: the kinds of field the service tests run on (the
  default atlas, the paper's single chart), the library field that answers the
  same, the paper's rays;
* :mod:`tests.harness.service`: apps started in-process, uploads that go on while
  servers are killed and the check of what they stored, snapshots retried while
  another writer holds the lease;
* :mod:`tests.harness.storage`: checks both storage backends' tests run;
* :mod:`tests.harness.cluster`: rays over every chart and front processes on one
  Ray cluster, for the cluster tests;
* :mod:`tests.harness.hostile`: hand-made and fuzzed hostile ``.npy``/``.npz`` bodies;
* :mod:`tests.harness.cells`, :mod:`tests.harness.charts`, :mod:`tests.harness.fig11`:
  answers compared cell by cell, rays stored in one chart alone, the paper's Fig. 11
  rays.

Test modules import helpers from here, never from one another.

The tests import it as ``tests.harness`` (``tests`` is a package, so pytest
puts the repository root on ``sys.path``); the benchmarks, run as scripts from
the repository root, put the root there through ``benchmarks/timing.py``.
"""
