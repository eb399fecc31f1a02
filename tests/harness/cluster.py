"""Helpers of the cluster tests: rays that land in every chart of a covering atlas
and front processes started on one database and one Ray cluster."""
from __future__ import annotations

import contextlib

from tests.harness.process import ServerProcess


def sphere_rays(rng, n):
    """Rays in every direction (they land in every chart of a covering atlas)."""
    return rng.normal(size=(n, 3)), rng.normal(size=(n, 3))


class Fronts:
    """Front processes on one database and one Ray cluster (killed when the test ends)."""

    def __init__(self, tmp, url: str, address: str, stack: contextlib.ExitStack, **options):
        self.tmp, self.url, self.address, self.stack = tmp, url, address, stack
        self.options = {"snapshot_every": 0, "ray_shards": 4, "ray_shard_memory": 1 << 30,
                        **options}
        self.n = 0

    def start(self, address: str | None = None) -> ServerProcess:
        self.n += 1
        srv = self.stack.enter_context(ServerProcess(
            self.tmp / f"front{self.n}", self.tmp / f"front{self.n}.log", database_url=self.url,
            ray=address or self.address, **self.options))
        srv.wait_ready(180)
        return srv

    def logs(self) -> str:
        return "\n".join(f"--- front{i} ---\n" + (self.tmp / f"front{i}.log").read_text()[-4000:]
                         for i in range(1, self.n + 1))
