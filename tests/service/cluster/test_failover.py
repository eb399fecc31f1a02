"""Failover (``flatserve/service/cluster/front/failover.py``) against a transport of
this process: coroutines stand for the copies' calls (no Ray: the cluster tests run
the real one). One live copy of each group answers; a lost copy's call is cancelled
and passed over, a restoring one passed over, a worker's own error is the request's.
"""
from __future__ import annotations

import asyncio

import pytest

from flatserve.service.cluster import wire
from flatserve.service.cluster.front import failover
from flatserve.service.status import NotReadyError, ShardUnavailableError

HANG = object()  # a copy that never answers


class Transport:
    """:class:`~flatserve.service.cluster.front.transport.RayTransport`'s surface: an
    actor is what its call does (a value, an exception, or :data:`HANG`)."""

    lost = (ConnectionError, asyncio.TimeoutError)

    def __init__(self) -> None:
        self.cancelled: list = []
        self.submitted: list = []

    def submit(self, actor, call):
        async def run():
            await asyncio.sleep(0)
            if actor is HANG:
                await asyncio.Event().wait()
            if isinstance(actor, Exception):
                raise actor
            return actor

        self.submitted.append(actor)
        return asyncio.ensure_future(run())

    async def aget(self, ref, timeout):
        return await asyncio.wait_for(asyncio.shield(ref), timeout)

    @staticmethod
    def result(call, value):
        return value

    def cancel(self, refs) -> None:
        for r in refs:
            if not r.done():
                self.cancelled.append(r)
                r.cancel()


class Groups:
    """:class:`~flatserve.service.cluster.front.failover.Copies`: ``actors[g][j]``,
    tried in order; marks kept."""

    def __init__(self, actors) -> None:
        self.actors, self.transport = actors, Transport()
        self.marks: dict = {}

    def order(self, g):
        return list(range(len(self.actors[g])))

    def actor(self, g, j):
        return self.actors[g][j]

    def mark(self, g, j, alive):
        self.marks[g, j] = alive

    def unavailable(self, g, last):
        return ShardUnavailableError(f"group {g} has no live copy ({last})")


def _call(groups, timeout=5.0):
    return failover.call(groups, {g: wire.status() for g in range(len(groups.actors))}, timeout)


def test_every_group_answers_from_its_first_live_copy():
    groups = Groups([["a0", "a1"], ["b0"]])
    assert _call(groups) == {0: "a0", 1: "b0"}
    assert groups.transport.submitted == ["a0", "b0"]  # the second copy never asked
    assert groups.marks == {(0, 0): True, (1, 0): True}


def test_a_lost_copy_is_marked_and_passed_over():
    groups = Groups([[ConnectionError("actor died"), "a1"]])
    assert _call(groups) == {0: "a1"}
    assert groups.marks == {(0, 0): False, (0, 1): True}


def test_a_copy_that_times_out_has_its_call_cancelled_and_the_next_copy_answers():
    groups = Groups([[HANG, "a1"]])
    assert _call(groups, timeout=0.2) == {0: "a1"}
    (ref,) = groups.transport.cancelled  # the hung copy is not left computing
    assert ref.cancelled()
    assert groups.marks == {(0, 0): False, (0, 1): True}


def test_a_restoring_copy_is_passed_over_but_not_marked_lost():
    groups = Groups([[ShardUnavailableError("restoring"), "a1"]])
    assert _call(groups) == {0: "a1"}
    assert groups.marks == {(0, 1): True}


def test_a_group_with_no_copy_left_fails_the_request_naming_why():
    groups = Groups([["a0"], [ConnectionError("gone"), ShardUnavailableError("behind")]])
    with pytest.raises(ShardUnavailableError, match=r"group 1 has no live copy \(behind\)"):
        _call(groups)


@pytest.mark.parametrize("own", [ValueError("bad rows"), NotReadyError("not ready")])
def test_a_workers_own_error_is_the_requests_and_the_other_calls_are_cancelled(own):
    groups = Groups([[own, "a1"], [HANG]])
    with pytest.raises(type(own), match=str(own)):
        _call(groups)
    assert "a1" not in groups.transport.submitted  # never retried elsewhere
    assert len(groups.transport.cancelled) == 1  # the other group's call
