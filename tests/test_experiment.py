"""Paper Sec. 4.3 as a test, and the `flatserve experiment` command."""
import pytest

from flatserve import cli
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
