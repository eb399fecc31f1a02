"""What a field's triangulations cost in cells, in one place: the cells per sample of a
Delaunay triangulation by dimension, which both guards of ``max_simplices`` use: the
upload guard (:mod:`.uploads`: a batch expected to pass the limit is refused) and the
create guard (:func:`check_capacity`, called by :mod:`.fields`: a field of a kind that
could not hold ``min_field_samples`` samples under the limit is refused when created).
The copies a sample takes are the library's (``copies``, :func:`flatserve.contract.
expected_copies`): no kind of field is special here."""
from __future__ import annotations

from typing import NamedTuple

from ...contract import SampledField, expected_copies
from .specs import kind_of
from ..settings import Settings
from ..status import CostLimitError

#: Cells of a Delaunay triangulation per sample by dimension D (uniform points,
#: measured with flatserve.Triangulation: 5,000 points for D <= 3, 200 for D = 8;
#: D = 1 exact); the estimate of a field with fewer than COST_MIN_SAMPLES samples.
CELLS_PER_SAMPLE = {1: 1.0, 2: 2.0, 3: 6.6, 4: 28.0, 5: 129.0, 6: 512.0, 7: 1704.0,
                    8: 5195.0}
#: A field's own cells per sample count once it holds this many samples.
COST_MIN_SAMPLES = 1000


def cells_per_sample(D: int) -> float:
    """:data:`CELLS_PER_SAMPLE` of dimension ``D``; beyond the table 3 times more per
    dimension (the growth from D = 7 to 8)."""
    return CELLS_PER_SAMPLE.get(D, CELLS_PER_SAMPLE[8] * 3.0 ** (D - 8))


class Capacity(NamedTuple):
    """The samples a field could hold under a limit of cells, before it holds any."""

    #: ``max_simplices / (per_sample * copies)``
    samples: float
    #: :func:`cells_per_sample` of the field's triangulation dimension
    per_sample: float
    #: shards holding a sample on average (:func:`flatserve.contract.expected_copies`)
    copies: float


def capacity(field: SampledField, max_simplices: int) -> Capacity:
    """The samples ``field`` could hold under ``max_simplices`` cells in all."""
    per, copies = cells_per_sample(field.ndim), expected_copies(field)
    return Capacity(max_simplices / (per * copies), per, copies)


def check_capacity(name: str, field: SampledField, settings: Settings) -> Capacity:
    """The :func:`capacity` of a field being created, refused when below
    ``min_field_samples``.

    Raises
    ------
    CostLimitError
        413 (it can never pass under these settings), naming the field, its kind
        (k, d), its dimension D, the estimate and the two settings to change.
    """
    cap = capacity(field, settings.max_simplices)
    least = settings.min_field_samples
    if cap.samples >= least:
        return cap
    D = field.ndim
    held = (f" x {cap.copies:.2f} charts holding each sample" if len(field.shards) > 1
            else "")
    raise CostLimitError(
        f"field {name!r} of {kind_of(field.k, field.d)} could hold only about "
        f"{cap.samples:,.0f} samples: its triangulations have dimension D = {D} "
        f"({cap.per_sample:,.0f} cells per sample{held}) and max_simplices is "
        f"{settings.max_simplices:,} cells; at least min_field_samples = {least:,} are "
        f"required: raise FLATSERVE_MAX_SIMPLICES (to at least "
        f"{least * cap.per_sample * cap.copies:,.0f}) or lower FLATSERVE_MIN_FIELD_SAMPLES")
