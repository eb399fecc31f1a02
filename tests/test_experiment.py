"""Paper Sec. 4.3 as a test, and the `flatserve experiment` command."""
import itertools

import numpy as np
import pytest

from flatserve import cli, experiment
from flatserve.basis import Basis
from flatserve.coordinates import n_equations
from flatserve.experiment import CASES, EXPERIMENT_TOL, run


@pytest.mark.parametrize("d,k", CASES)
def test_recovers_every_coefficient(d, k):
    row = run(d, k, trials=500, seed=1000 + 10 * d + k)
    assert (row.d, row.k, row.m, row.trials) == (d, k, (k + 1) * (d - k) + 1, 500)
    assert row.failures == 0
    assert row.max_error <= EXPERIMENT_TOL


def test_cases_cover_the_issue():
    assert set(CASES) >= {(2, 1), (3, 1), (3, 2), (4, 1), (4, 2), (5, 2), (6, 3)}


def test_seed_is_reproducible():
    assert run(3, 1, trials=20, seed=5) == run(3, 1, trials=20, seed=5)


def test_cli_prints_table(capsys):
    assert cli.main(["experiment", "--trials", "20", "--seed", "3"]) == 0
    out = capsys.readouterr().out
    lines = [l.split() for l in out.splitlines() if l[:3].strip().isdigit()]
    assert [(int(l[0]), int(l[1])) for l in lines] == list(CASES)
    assert all(int(l[3]) == 20 and int(l[5]) == 0 and float(l[4]) <= EXPERIMENT_TOL for l in lines)


def test_cli_rejects_bad_trials(capsys):
    assert cli.main(["experiment", "--trials", "0"]) == 2
    with pytest.raises(SystemExit):
        cli.main(["experiment", "--trials", "many"])


#: Beyond the paper's table: the cases where some picks of index sets give a
#: degenerate basis (the issue's (5, 1), (5, 3), (6, 1), (6, 2)) and more.
MORE_CASES = [(5, 1), (5, 3), (6, 1), (6, 2), (7, 1), (7, 3)]


@pytest.mark.parametrize("d,k", MORE_CASES)
def test_every_case_recovers_every_coefficient_with_degenerate_bases_redrawn(d, k):
    row = run(d, k, trials=10_000, seed=1)
    assert row.failures == 0, row
    assert row.max_error <= EXPERIMENT_TOL


def test_the_issues_failing_run_now_redraws_its_degenerate_bases():
    """run(5, 1, trials=2000, seed=1) reported 28 failures: each was a degenerate
    basis (the library rightly said SINGULAR); now redrawn and counted."""
    row = run(5, 1, trials=2000, seed=1)
    assert row.failures == 0 and row.redrawn >= 28


def test_what_is_redrawn_is_what_basis_check_refuses():
    """A second implementation: the trials flagged degenerate are exactly those
    whose flats :meth:`Basis.check` refuses (check 3, the barycentre)."""
    rng = np.random.default_rng(7)
    d, k = 5, 1
    m = n_equations(k, d)
    combos = np.array(list(itertools.combinations(range(d + 1), k + 1)))
    Qb, rb = experiment._bases(rng, 600, d, k, combos, m)
    flagged = experiment._degenerate(Qb, rb, k, experiment.SINGULAR_RCOND)
    assert 1 <= flagged.sum() < 60  # some, not most: the check has a subject
    for i in range(len(Qb)):
        ok = Basis(Qb[i], rb[i], k).check().ok
        assert ok == (not flagged[i]), i


def test_cli_cases(capsys):
    assert cli.main(["experiment", "--trials", "50", "--cases", "5,1", "6,2"]) == 0
    out = capsys.readouterr().out
    lines = [l.split() for l in out.splitlines() if l[:3].strip().isdigit()]
    assert [(int(l[0]), int(l[1])) for l in lines] == [(5, 1), (6, 2)]
    assert all(int(l[3]) == 50 and int(l[5]) == 0 for l in lines)


@pytest.mark.parametrize("cases, message", [
    (["3,3"], "k: need 0 <= k < d = 3"),
    (["30,14"], "index sets of size k+1; at most"),
    (["40,1"], "trials: 1000 trials of (d, k) = (40, 1) hold"),
])
def test_cli_refuses_cases_it_cannot_run(capsys, cases, message):
    assert cli.main(["experiment", "--cases", *cases]) == 2
    assert message in capsys.readouterr().err


def test_cli_refuses_a_malformed_case(capsys):
    with pytest.raises(SystemExit):
        cli.main(["experiment", "--cases", "3"])
    assert "expected D,K" in capsys.readouterr().err
