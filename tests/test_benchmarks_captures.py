"""The benchmark runs of rendered captures (`test_benchmarks.CAPTURES`): `tests/test_benchmarks.py`'s
smoke test, in a file of its own so that `make test`'s two workers (`--dist loadfile`) each start on
one half of the benchmarks instead of one worker running them all."""

import pytest
from test_benchmarks import CAPTURES, RUNS, check_run, ran  # noqa: F401  (`ran`: the module's fixture)


@pytest.mark.parametrize("name", [n for n, r in RUNS.items() if r.process in CAPTURES])
def test_benchmark_runs_at_its_smallest_size(name, ran):  # noqa: F811
    check_run(name, ran)
