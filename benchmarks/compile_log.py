"""Where the test suite's time goes: every XLA compilation, by program and by test.

    COMPILE_LOG=/tmp/clog PYTHONPATH=benchmarks python -m pytest -p compile_log
    python benchmarks/compile_log.py /tmp/clog [--out benchmarks/results]

As a pytest plugin (``-p compile_log``), each worker appends ``seconds, program, test`` for
every XLA compilation to ``$COMPILE_LOG.<worker>`` (JAX's ``jax_log_compiles``; programs
found in the persistent cache are not compiled and not logged). Run as a script, it sums
the logs by program and by test into ``suite_compiles-<host>.md``. Subprocesses (the
command-line tests, the notebooks' kernels) are not seen.
"""

import os
import re
import sys

_current = ["?"]


def pytest_configure(config):
    import logging

    import jax

    if not os.environ.get("COMPILE_LOG"):
        return
    jax.config.update("jax_log_compiles", True)
    out = open(f"{os.environ['COMPILE_LOG']}.{os.environ.get('PYTEST_XDIST_WORKER', 'main')}", "a")

    class Keep(logging.Handler):
        def emit(self, record):
            m = re.match(r"Finished XLA compilation of (.*) in ([0-9.e-]+) sec", record.getMessage())
            if m:
                out.write(f"{m.group(2)}\t{m.group(1)}\t{_current[0]}\n")
                out.flush()

    logging.getLogger("jax._src.dispatch").addHandler(Keep(level=logging.WARNING))


def pytest_runtest_setup(item):
    _current[0] = item.nodeid


def main():
    import argparse
    import collections
    import glob

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from shell_timing import report

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("log", help="the COMPILE_LOG prefix the plugin wrote to")
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--top", type=int, default=25)
    a = p.parse_args()
    rows = [line.rstrip("\n").split("\t") for f in glob.glob(a.log + ".*") for line in open(f)]
    by_program, by_test = collections.defaultdict(list), collections.defaultdict(list)
    for seconds, program, test in rows:
        by_program[program].append(float(seconds))
        by_test[test].append(float(seconds))
    total = sum(float(r[0]) for r in rows)
    big = sum(float(r[0]) for r in rows if float(r[0]) >= 1.0)
    top = sorted(by_program.items(), key=lambda kv: -sum(kv[1]))[: a.top]
    tests = sorted(by_test.items(), key=lambda kv: -sum(kv[1]))[: a.top]
    intro = (f"`COMPILE_LOG=/tmp/clog PYTHONPATH=benchmarks python -m pytest -p compile_log` (fresh cache), then "
             f"`python benchmarks/compile_log.py /tmp/clog` (the suite's two workers each pinned to a core by tests/conftest.py): {len(rows)} compilations, {total:.0f} s of worker "
             f"time, {big:.0f} s of it in {sum(float(r[0]) >= 1.0 for r in rows)} compilations of 1 s or more. "
             f"By program (top {a.top}), then by test.")
    table = [(name, len(s), round(sum(s), 1), round(sum(s) / len(s), 2)) for name, s in top]
    table += [("**by test**", "", "", "")] + [(t, len(s), round(sum(s), 1), round(sum(s) / len(s), 2)) for t, s in tests]
    print(report(a.out, "suite_compiles", "XLA compilation in the test suite", intro,
                 ["program / test", "compilations", "seconds", "mean (s)"], table))


if __name__ == "__main__":
    main()
