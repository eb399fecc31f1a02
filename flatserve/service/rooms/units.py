"""A stored batch's unit of length: the field rule every applier of the log follows.

A field whose unit of length is chosen from its data (an atlas field made with
``unit="auto"``, :attr:`flatserve.atlas_field.AtlasField.unit_from_data`)
takes it from its first batch. The replica that stores a batch records the
unit it chose with it (:func:`..log.blobs.split_batch`); every process that applies
the log (a replica's applier, :mod:`.applier`; a shard worker,
:mod:`..cluster.worker.shard`; a cluster front's field, :mod:`..cluster.front.remote`) takes
that recorded unit, so that they all chart the first batch alike. This module
imports nothing of theirs: each of them imports it.
"""
from __future__ import annotations

from ...atlas_field import choose_unit
from ...flats import Flats


def adopt_unit(field, unit: float | None) -> None:
    """The unit recorded with a stored batch (:func:`..log.blobs.split_batch`): a field
    whose unit is chosen from the data and that has inserted no batch yet takes it
    (:meth:`flatserve.atlas_field.AtlasField.settle_unit`), so that it charts its
    first batch in the unit the replica that stored the batch chose, not one of
    its own (a replica, a restart, a shard of a cluster). Other fields: nothing."""
    if unit is not None and field.unit_from_data:
        field.settle_unit(unit, if_empty=True)


def batch_unit(field, flats: Flats, values, unit: float | None) -> float | None:
    """The unit a stored batch gives a field whose unit is still to be chosen: the
    one recorded with it (``unit``, :func:`..log.blobs.split_batch`), or for a batch
    stored without one (by an older server) the one the field chooses from its
    rows (:func:`flatserve.atlas_field.choose_unit`), as every shard worker does."""
    if unit is None and field.unit_pending:
        return choose_unit(field.atlas, flats, values)
    return unit


def unit_of(field) -> float | None:
    """An atlas field's unit of length; None while it is still to be chosen (or for a
    field without one)."""
    return field.unit
