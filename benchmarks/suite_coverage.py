"""Which default-run tests execute lines of the package that no other default-run test
executes: line coverage with one context per test, against each test's time.

    pip install coverage pytest-cov
    COVERAGE_CORE=ctrace python -m pytest -q --durations=0 --cov=dtwin_jax --cov-context=test \
        --cov-config=COVRC --cov-report= > DURATIONS.txt
    python benchmarks/suite_coverage.py .coverage DURATIONS.txt [--min-seconds 4]

`COVRC` holds `[run] parallel = true` and `patch = subprocess` (lines run by the
processes a test starts are measured too, without its context). `ctrace`: the default
`sysmon` core does not record per-test contexts. Tests in order of time, longest first:
each is dropped when every line it executes is executed by a test still kept; what it
executes alone is printed beside it. A test with no line of its own may still be the only
check of what it asserts (an accuracy, an equality, a rate), and a test that starts processes
may run lines there that no other test runs (they are counted as `<subprocess>`'s).
"""

import argparse
import collections
import re

from coverage import CoverageData


def _lines(path: str) -> dict:
    """`(file, line) -> {test}`; lines run in a started process count as `<subprocess>`."""
    data = CoverageData(basename=path)
    data.read()
    cover = {}
    for f in data.measured_files():
        for line, contexts in data.contexts_by_lineno(f).items():
            cover[(f, line)] = {c.rsplit("|", 1)[0] if c else "<subprocess>" for c in contexts}
    return cover


def _durations(path: str) -> dict:
    """Each test's setup, call and teardown seconds, summed, from pytest's `--durations=0`."""
    seconds = collections.defaultdict(float)
    with open(path) as f:
        for line in f:
            m = re.match(r"^([0-9.]+)s (call|setup|teardown)\s+(\S+)", line)
            if m:
                seconds[m.group(3)] += float(m.group(1))
    return seconds


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("coverage_file")
    ap.add_argument("durations")
    ap.add_argument("--min-seconds", type=float, default=4.0)
    a = ap.parse_args()
    cover, seconds = _lines(a.coverage_file), _durations(a.durations)
    alone = collections.Counter(next(iter(v)) for v in cover.values() if len(v) == 1)
    dropped, saved = set(), 0.0
    for test in sorted(seconds, key=lambda t: -seconds[t]):
        if seconds[test] < a.min_seconds:
            break
        own = sum(1 for v in cover.values() if test in v and not v - dropped - {test})
        print(f"{seconds[test]:6.1f} s  {own:4d} lines of its own ({alone[test]} alone)  {test}")
        if not own:
            dropped.add(test)
            saved += seconds[test]
    total = sum(seconds.values())
    print(f"{len(dropped)} tests of {a.min_seconds:g} s or more, {saved:.0f} s of {total:.0f} s, "
          f"execute no line that the tests kept do not")


if __name__ == "__main__":
    main()
