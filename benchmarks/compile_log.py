"""Where the test suite's time goes: every trace, lowering and XLA compilation, by program
and by test.

    COMPILE_LOG=/tmp/clog PYTHONPATH=benchmarks python -m pytest -p compile_log
    python benchmarks/compile_log.py /tmp/clog [--out benchmarks/results]

As a pytest plugin (``-p compile_log``), each worker appends ``seconds, phase, program,
test`` to ``$COMPILE_LOG.<worker>`` for every top-level trace (``trace``), lowering to MLIR
(``lower``) and XLA compilation (``compile``) that JAX logs (``jax_log_compiles``), and a
``hit`` row for every program found in the persistent cache (the ``compile`` row that
follows it is then its load time, summed apart), and a ``write`` row with the cache key for
every program written to the persistent cache (a key written twice is a program compiled
twice, by both workers or by one); each row ends with the call site, the
innermost frame of the package (outside ``dtwin_jax/_compile``), the tests or the
benchmarks. Run as a script, it sums the logs by phase, by program, by call site and by
test into ``suite_compiles-<host>.md``. Subprocesses (the command-line tests, the notebooks'
kernels) are not seen.
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
    prefix = f"{os.environ['COMPILE_LOG']}.{os.environ.get('PYTEST_XDIST_WORKER', 'main')}"
    out = open(prefix, "a")
    # Apart, so the timing rows keep their five columns: what each compiled program was
    # keyed on (its argument shapes), to see why a program compiles again.
    shapes = open(prefix + ".shapes", "a")

    phases = (("trace", r"Finished tracing (.*) for jit in ([0-9.e-]+) sec"),
              ("lower", r"Finished jaxpr to MLIR module conversion (.*) in ([0-9.e-]+) sec"),
              ("compile", r"Finished XLA compilation of (.*) in ([0-9.e-]+) sec"))

    class Keep(logging.Handler):
        def emit(self, record):
            message = record.getMessage()
            if message.startswith("Compiling ") and " with global shapes and types " in message:
                head, rest = message[len("Compiling "):].split(" with global shapes and types ", 1)
                shapes.write(f"{head}\t{_current[0]}\t{_call_site()}\t{rest.split('. Argument mapping')[0]}\n")
                shapes.flush()
                return
            if message.startswith("Persistent compilation cache hit"):
                out.write(f"0\thit\t{message.split(chr(39))[1]}\t{_current[0]}\t{_call_site()}\n")
                return
            for phase, pattern in phases:
                m = re.match(pattern, message)
                if m:
                    out.write(f"{m.group(2)}\t{phase}\t{m.group(1)}\t{_current[0]}\t{_call_site()}\n")
                    out.flush()
                    return

    keep = Keep(level=logging.WARNING)  # jax_log_compiles logs all of these at WARNING
    for name in ("jax._src.dispatch", "jax._src.compiler", "jax._src.interpreters.pxla"):
        logging.getLogger(name).addHandler(keep)

    class Written(logging.Handler):
        """Every persistent-cache write, by key: a key written by both workers is a program
        compiled twice (JAX logs the write at DEBUG)."""

        def emit(self, record):
            message = record.getMessage()
            if message.startswith("Writing ") and " with key " in message:
                out.write(f"0\twrite\t{message.split(' with key ')[1].strip(chr(39))}\t{_current[0]}\t{_call_site()}\n")
                out.flush()

    cache_log = logging.getLogger("jax._src.compilation_cache")
    cache_log.addHandler(Written(level=logging.DEBUG))
    cache_log.setLevel(logging.DEBUG)


def _call_site() -> str:
    """The innermost frame of the package (not its ``_compile`` wrappers), the tests or the
    benchmarks: ``path:line``. Logging handlers run in the thread that logs, so the stack
    is the compiling call's."""
    import traceback

    for frame in reversed(traceback.extract_stack()):
        path = frame.filename.replace(os.sep, "/")
        for root in ("/dtwin_jax/", "/tests/", "/benchmarks/"):
            if root in path and "/_compile/" not in path and not path.endswith("compile_log.py"):
                return path[path.rindex(root) + 1:] + f":{frame.lineno}"
    return "?"


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
    rows, written = [], collections.Counter()
    for f in (f for f in glob.glob(a.log + ".*") if not f.endswith(".shapes")):
        hit = False
        for line in open(f):
            row = line.rstrip("\n").split("\t")
            if len(row) == 4:  # a log from before call sites
                row.append("?")
            if len(row) != 5:
                continue
            if row[1] == "write":
                written[row[2]] += 1
                continue
            if row[1] == "compile" and hit:  # the hit is logged inside the compile step it ends
                row[1] = "load"
            hit = row[1] == "hit"
            rows.append(row)
    phase_seconds = collections.Counter()
    phase_count = collections.Counter()
    for seconds, phase, *_ in rows:
        phase_seconds[phase] += float(seconds)
        phase_count[phase] += 1
    compiles = [r for r in rows if r[1] == "compile"]
    by_program, by_test, by_site = (collections.defaultdict(list) for _ in range(3))
    for seconds, _, program, test, site in compiles:
        by_program[program].append(float(seconds))
        by_test[test].append(float(seconds))
        by_site[f"{program} at {site}"].append(float(seconds))
    total = phase_seconds["compile"]
    big = sum(float(r[0]) for r in compiles if float(r[0]) >= 1.0)
    top = sorted(by_program.items(), key=lambda kv: -sum(kv[1]))[: a.top]
    tests = sorted(by_test.items(), key=lambda kv: -sum(kv[1]))[: a.top]
    sites = sorted(by_site.items(), key=lambda kv: -sum(kv[1]))[: a.top]
    intro = (f"`COMPILE_LOG=/tmp/clog PYTHONPATH=benchmarks python -m pytest -p compile_log` (fresh cache), then "
             f"`python benchmarks/compile_log.py /tmp/clog` (the suite's two workers each pinned to a core by "
             f"tests/conftest.py). Worker time by phase: tracing {phase_seconds['trace']:.0f} s "
             f"({phase_count['trace']} top-level traces), lowering {phase_seconds['lower']:.0f} s "
             f"({phase_count['lower']}), XLA compilation {total:.0f} s ({phase_count['compile']}), loading from "
             f"the persistent cache {phase_seconds['load']:.0f} s ({phase_count['load']}); {big:.0f} s in "
             f"{sum(float(r[0]) >= 1.0 for r in compiles)} compilations of 1 s or more; "
             f"{sum(written.values())} cache writes of {len(written)} distinct programs "
             f"({sum(n > 1 for n in written.values())} written more than once). "
             f"Compilations by program (top {a.top}), by program and call site, then by test.")
    table = [(name, len(s), round(sum(s), 1), round(sum(s) / len(s), 2)) for name, s in top]
    for title, group in (("**by call site**", sites), ("**by test**", tests)):
        table += [(title, "", "", "")] + [(t, len(s), round(sum(s), 1), round(sum(s) / len(s), 2)) for t, s in group]
    print(report(a.out, "suite_compiles", "XLA compilation in the test suite", intro,
                 ["program / test", "compilations", "seconds", "mean (s)"], table))


if __name__ == "__main__":
    main()
