"""Following one structure in service, window after window (formats.md, "Monitoring a
structure in service").

Each window is first tested against the twin as it stood before it
(`change.window_test`; a change that persists also by the window
pooled with up to four before it, `pooled_tests`; false-alarm rate `false_alarm`
per window), then absorbed: without an alarm the twin is re-updated with the older data
discounted by `forget`; after an alarm it restarts from the nominal prior on the window
alone, and the alarm names its reasons (terms that appeared or disappeared, coefficients that
left their 95% interval). Every window's entry rides in the twin's history, so the twin
folder keeps the timeline, and a window whose data are already there is never absorbed
twice (a killed monitor resumes where it stopped, with the history it would have had).
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from dtwin_jax.errors import DataError
from dtwin_jax.io.twin_files import MAX_RECENT, RECENT_KINDS, SPREAD_KIND
from dtwin_jax.monitor.change import (
    linear_columns,
    overdispersion,
    window_statistics,
    window_test,
)
from dtwin_jax.sampler import SuffStats
from dtwin_jax.update.from_data import update_from_data
from dtwin_jax.update.lifecycle import arrays_sha256
from dtwin_jax.update.result import SamplerSettings, UpdateResult

__all__ = ["FALSE_ALARM", "LOOKBACK", "MONITOR_SETTINGS", "Monitor", "alarm_reasons", "combined_p_value",
           "data_fingerprint", "first_alarm", "pooled_tests", "recent_windows", "timeline_dispersion", "window_estimates",
           "window_spread"]

# Two chains of 1000 draws after 250 sweeps of burn-in: a 1 s window tested and absorbed in
# about 0.2 s warm on one core. The chains start at greedy modes; 500 sweeps of burn-in
# changed no PIP by more than 0.004 (Monte Carlo error between seeds: 0.013) and cost 11%.
MONITOR_SETTINGS = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=250)
RESTART_PRIOR = "spike-and-slab (restarted: the window disagreed with the twin)"
# The default false-alarm rate per window, by framework. An output-only window's rows come
# from states estimated from accelerations and a diffusion's approximation, and its test runs
# above its nominal rate on long windows (2 alarms in 200 stationary 40 s windows at 0.001):
# it is asked for half (docs/monitoring.md, "Output-only: accelerometers alone").
FALSE_ALARM = {"input-output": 1e-3, "output-only": 5e-4}
# A change that persists is also tested on this window pooled with up to LOOKBACK - 1 windows
# before it (since the last restart), against the twin as it stood before the oldest of them.
LOOKBACK = MAX_RECENT + 1


def recent_windows(result: UpdateResult) -> list[tuple[SuffStats, SuffStats, SuffStats]]:
    """A monitored twin's last windows, newest first.

    **Arguments:**

    - `result`: the monitored twin, an `UpdateResult` (its stored recent windows' statistics).

    **Returns:** a list, newest first, of `(window, twin, spread)` `SuffStats` triples batched over
    the `q` drift equations: each window's drift statistics, the twin's before it and the window's
    score spread (`window_spread`); at most `MAX_RECENT`, empty after a restart.
    """
    kinds = [result.statistics.get(kind) for kind in RECENT_KINDS]
    if any(k is None for k in kinds):
        return []
    return [tuple(SuffStats(*(np.asarray(a)[j] for a in s)) for s in kinds) for j in range(np.shape(kinds[0].n)[0])]


def window_spread(result: UpdateResult) -> SuffStats:
    """The covariance of the last update's window's drift score over draws of its states' error.

    **Arguments:**

    - `result`: the update with the window, an `UpdateResult`.

    **Returns:** a `SuffStats` (float64 NumPy arrays) as the update stored it, the covariance its
    `gram` `(q, K, K)`; zeros where the states were not estimated.
    """
    spread = result.statistics.get(SPREAD_KIND)
    if spread is not None:
        return _stats(spread)
    q, K = np.shape(result.statistics["drift"].xty)
    return SuffStats(np.zeros((q, K, K)), np.zeros((q, K)), np.zeros(q), np.zeros(q))


def _with_recent(statistics: dict, recent: list[tuple[SuffStats, SuffStats, SuffStats]]) -> dict:
    """`statistics` with `recent` (newest first) as the store keeps it."""
    out = {k: v for k, v in statistics.items() if k not in RECENT_KINDS}
    if recent:
        for i, kind in enumerate(RECENT_KINDS):
            out[kind] = SuffStats(*(np.stack([np.asarray(getattr(r[i], f)) for r in recent]) for f in SuffStats._fields))
    return out


def _stats(s) -> SuffStats:
    return SuffStats(*(np.asarray(a, dtype=float) for a in s))


def pooled_tests(twin: SuffStats, window: SuffStats, recent: list[tuple[SuffStats, SuffStats, SuffStats]],
                 dispersion=1.0, spread: SuffStats | None = None, linear=False) -> list:
    """The window against the twin before it, then pooled with the windows before it.

    The window alone is tested against `twin`; the window pooled with the `1 .. len(recent)`
    windows before it, against the twin before the oldest of those. Each test adds the pooled
    windows' score spreads to `V`.

    **Arguments:**

    - `twin`: the twin's drift statistics before the window, a `SuffStats` batched over the `q`
      drift equations.
    - `window`: the window's own drift statistics, likewise.
    - `recent`: the windows before it, newest first (`recent_windows`): `(window, twin before
      it, score spread)` triples; a spread of None adds nothing.
    - `dispersion`: `()` or `(q,)`, the factor on `V` (`change.overdispersion`); default 1.
    - `spread`: this window's score spread (`window_spread`), or None (default): none.
    - `linear`: `(q, K)` or `(K,)` bool, or False (default): the nominal's linear columns
      (`change.linear_columns`).

    **Returns:** a list of `1 + len(recent)` `change.ChangeTest`s: the window alone, then pooled
    with 1, 2, ... windows before it.
    """
    omega = 0.0 if spread is None else np.asarray(spread.gram)
    tests, pooled = [window_test(twin, window, dispersion, omega, linear)], window
    for w, before, s in recent:
        pooled = SuffStats(*(np.asarray(x) + np.asarray(y) for x, y in zip(pooled, w)))
        omega = omega if s is None else omega + np.asarray(s.gram)
        tests.append(window_test(before, pooled, dispersion, omega, linear))
    return tests


def timeline_dispersion(timeline: list[dict], num_equations: int) -> np.ndarray:
    """`change.overdispersion` of each drift equation from the timeline's windows without an alarm.

    **Arguments:**

    - `timeline`: the monitor's window entries (`Monitor.timeline`), whose `test` holds the
      unscaled `T` (`statistic` times `dispersion`) of each equation.
    - `num_equations`: the number `q` of drift equations; windows whose `test` has another number
      of entries are skipped.

    **Returns:** the factor on `V`, `(q,)`, at least 1.
    """
    total, count = np.zeros(num_equations), np.zeros(num_equations)
    for w in timeline:
        tests = w.get("test")
        if w.get("alarm") or not isinstance(tests, list) or len(tests) != num_equations:
            continue
        for j, t in enumerate(tests):
            if t.get("df", 0) > 0:
                total[j] += t["statistic"] * t.get("dispersion", 1.0)
                count[j] += 1
    return np.asarray(overdispersion(total, count))


def test_p_value(test) -> float:
    """One test's p-value over every equation: the smallest times their number (Bonferroni).

    **Arguments:**

    - `test`: a `change.ChangeTest`, its `p_value` `(q,)`.

    **Returns:** the p-value, a float in [0, 1].
    """
    return float(min(1.0, np.min(np.asarray(test.p_value)) * np.size(test.p_value)))


def combined_p_value(tests) -> tuple[float, float]:
    """The alarm's p-value and the window's alone, from the pooled tests.

    **Arguments:**

    - `tests`: the `change.ChangeTest`s of `pooled_tests`, the window alone first.

    **Returns:** `(p, p_window)`: the alarm's p-value, the smallest of the tests' `test_p_value`
    times their number, and the window's alone (the first test's `test_p_value`), floats.
    """
    p = [test_p_value(t) for t in tests]
    return float(min(1.0, min(p) * len(p))), p[0]


def alarm_reasons(before: UpdateResult, after: UpdateResult) -> tuple[list[str], list[str], list[str]]:
    """What changed between two twins' drift equations, as `"state:term"` names.

    **Arguments:**

    - `before`: the twin before, an `UpdateResult`.
    - `after`: the twin after, an update over the same library.

    **Returns:** `(new, dropped, changed)`: terms selected after but not before, before but
    not after, and selected in both whose mean after lies outside their 95% HDI before.
    """
    old = {e.state: e for e in before.equations if e.kind == "drift"}
    new, dropped, changed = [], [], []
    for e in after.equations:
        b = old.get(e.state)
        if e.kind != "drift" or b is None:
            continue
        hdi = b.hdi_95
        for k, name in enumerate(e.names):
            label = f"{e.state}:{name}"
            if e.selected[k] and not b.selected[k]:
                new.append(label)
            elif b.selected[k] and not e.selected[k]:
                dropped.append(label)
            elif e.selected[k] and not hdi[k, 0] <= e.mean[k] <= hdi[k, 1]:
                changed.append(label)
    return new, dropped, changed


def data_fingerprint(data: dict) -> str:
    """SHA-256 of a window as read: `t`, `x`, `u`, `xdot` and the sensor names.

    **Arguments:**

    - `data`: the window, as `dtwin_jax.io.load_measurements` returns a file (a key that is
      missing or None counts as absent).

    **Returns:** the hex digest (`update.lifecycle.arrays_sha256`), equal for the same data read
    again.
    """
    names = "".join(f"{key}:{data.get(key)!r};" for key in ("x_names", "xdot_names"))
    return arrays_sha256({key: data.get(key) for key in ("t", "x", "u", "xdot")}, names)


def window_estimates(result: UpdateResult, window: SuffStats, also=()) -> list[dict]:
    """Each drift equation's coefficients from this window alone, with their standard errors.

    Least squares on the window's statistics over the twin's selected terms, every displacement's linear term
    (the stiffness, followed even while it is not selected) and the terms in `also`, with
    their standard errors from the window's own residual variance. Independent from window
    to window (the twin's posterior is not: it carries the older windows), so trends over
    service time are fitted to these (`dtwin_jax.monitor.degradation`).

    **Arguments:**

    - `result`: the twin after the window, an `UpdateResult`.
    - `window`: the window's own drift statistics, a `SuffStats` batched over the drift equations.
    - `also`: `(state, term)` pairs regressed as well (a monitor passes every term it regressed
      before, so that a term whose selection flips from window to window does not make the
      others' estimates jump: the track stays one model); default none.

    **Returns:** one `{"state", "terms": {term: [mean, sd]}}` per drift equation,
    acceleration units (`terms` empty where the window's Gram matrix over those terms is singular).
    """
    nominal = result.nominal
    linear = set(nominal.state_names[:nominal.d])  # the displacements q_1 .. q_d
    also = set(also)
    out = []
    for j, e in enumerate(e for e in result.equations if e.kind == "drift"):
        index = [k for k, name in enumerate(e.names)
                 if e.selected[k] or name in linear or (e.state, name) in also]
        G = np.asarray(window.gram[j])[np.ix_(index, index)]
        b = np.asarray(window.xty[j])[index]
        n = float(np.asarray(window.n[j]))
        try:
            beta = np.linalg.solve(G, b)
            cov = np.linalg.inv(G)
        except np.linalg.LinAlgError:
            out.append({"state": e.state, "terms": {}})
            continue
        resid = max(float(np.asarray(window.yty[j])) - float(b @ beta), 0.0) / max(n - len(index), 1.0)
        sd = np.sqrt(np.maximum(np.diag(cov) * resid, 0.0))
        out.append({"state": e.state, "terms": {e.names[k]: [float(m), float(v)] for k, m, v in zip(index, beta, sd)}})
    return out


def _regressed(twin: UpdateResult, timeline: list[dict]) -> set[tuple[str, str]]:
    """`(state, term)` of the twin's selected drift terms and of every term an earlier
    window's estimates regressed."""
    terms = {(e.state, name) for e in twin.equations if e.kind == "drift"
             for name, chosen in zip(e.names, e.selected) if chosen}
    return terms | {(e["state"], name) for w in timeline for e in w.get("window_estimates", [])
                    for name in e.get("terms", {})}


def first_alarm(timeline: list[dict]) -> int | None:
    """The index of the first window with an alarm, or None.

    **Arguments:**

    - `timeline`: the monitor's window entries (`Monitor.timeline`), oldest first.

    **Returns:** the first alarm's window `index` (int), or None where no window raised one.
    """
    return next((w["index"] for w in timeline if w.get("alarm")), None)


@dataclasses.dataclass
class Monitor:
    """A twin that follows its structure: `step` tests and absorbs one window.

    **Arguments:**

    - `twin`: the baseline `update.UpdateResult` (a saved twin's
      `io.store.load_twin`, or a fresh update), either framework.
    - `false_alarm`: the chance that a window that follows the twin raises an alarm, in
      (0, 1) (split evenly over the drift equations); None: the twin's framework's
      `FALSE_ALARM` (0.001 input-output, 0.0005 output-only).
    - `forget`: the weight, in [0, 1], of the older windows' data at each update (0.9:
      about ten windows' memory, so a slow drift is followed).
    - `settings`: the sampler's, per window (default `MONITOR_SETTINGS`).
    - `seed`: window `h` of the history is sampled with seed `seed + h`, so a resumed
      run repeats an uninterrupted one.
    - `smoothing`: as `update.update_input_output`'s (default `"auto"`).
    """

    twin: UpdateResult
    false_alarm: float | None = None
    forget: float = 0.9
    settings: SamplerSettings = MONITOR_SETTINGS
    seed: int = 0
    smoothing: object = "auto"

    def __post_init__(self):
        if self.false_alarm is None:
            self.false_alarm = FALSE_ALARM[self.twin.mode]
        if not 0.0 < self.false_alarm < 1.0:
            raise DataError(f"the false-alarm rate must be in (0, 1), got {self.false_alarm:g}")
        if not 0.0 <= self.forget <= 1.0:
            raise DataError(f"forget must be in [0, 1], got {self.forget:g}")
        if not any(e.kind == "drift" for e in self.twin.equations):
            raise DataError("the twin has no drift equation to monitor")

    @property
    def timeline(self) -> list[dict]:
        """Every monitored window's entry (formats.md's `windows`), oldest first."""
        return [h["monitor"] for h in self.twin.history if isinstance(h, dict) and isinstance(h.get("monitor"), dict)]

    def absorbed(self, data: dict) -> bool:
        """Whether a window with exactly these data is already in the timeline.

        A resumed run skips such a window: no window counts twice.

        **Arguments:**

        - `data`: the window, as `dtwin_jax.io.load_measurements` returns a file.

        **Returns:** True where an entry of the timeline has the same `data_fingerprint`.
        """
        fp = data_fingerprint(data)
        return any(w.get("data_sha256") == fp for w in self.timeline)

    def _update(self, data: dict, source: str, previous, seed: int) -> UpdateResult:
        t = self.twin
        return update_from_data(t.mode, t.nominal, data, library=t.library,
                                diffusion_library=t.preprocessing.get("diffusion_library"), smoothing=self.smoothing,
                                source=source, pip_threshold=t.pip_threshold, settings=self.settings, seed=seed,
                                previous=previous, forget=self.forget)

    def step(self, data: dict, *, source: str = "window", t_start: float | None = None) -> dict:
        """Test the window `data` against the twin, then absorb it.

        **Arguments:**

        - `data`: the window, as `dtwin_jax.io.load_measurements` returns a file
          (`t`, `x`, `u`, `xdot`, `x_names`, `xdot_names`).
        - `source`: the window's name in the timeline (default `"window"`).
        - `t_start`: its start in service time, s (default its first sample time).

        **Returns:** the window's entry of the timeline (formats.md), also appended to the
        twin's history: `index`, `source`, `t_start`, `alarm`, `new_terms`,
        `dropped_terms`, `changed_terms`, `seconds`, `equations`, and `p_value` (the
        alarm's: `combined_p_value`), `p_window` (this window's alone, over every drift
        equation), `pooled` (the window alone, then pooled with 1, 2, ... windows before
        it), `test` (the window alone: each equation's statistic, degrees of freedom and
        p-values: the whole library's, the largest term's, the linear terms'),
        `restarted`, `window_estimates` (`window_estimates`) and `data_sha256`
        (`data_fingerprint`).
        """
        start = time.perf_counter()
        before = self.twin
        seed = self.seed + len(before.history)
        after = self._update(data, source, before, seed)
        twin, window = _stats(before.statistics["drift"]), window_statistics(after, before, self.forget)
        recent = recent_windows(before)
        timeline = self.timeline
        dispersion = timeline_dispersion(timeline, int(np.shape(twin.n)[0]))
        spread = window_spread(after)
        drift = [e for e in before.equations if e.kind == "drift"]
        linear = np.stack([linear_columns(e.names, before.nominal) for e in drift])
        tests = pooled_tests(twin, window, recent, dispersion, spread, linear)
        p_combined, p_window = combined_p_value(tests)
        stat, df, p_all, term, z, p_term, p_linear, p = (np.asarray(a) for a in tests[0])
        alarm = p_combined < self.false_alarm
        new = dropped = changed = []
        if alarm:  # the older data no longer describe the structure: start again from this window
            fresh = self._update(data, source, None, seed)
            entry = {**fresh.history[-1], "update": len(before.history) + 1, "prior": RESTART_PRIOR}
            after = dataclasses.replace(fresh, history=list(before.history) + [entry])
            new, dropped, changed = alarm_reasons(before, after)
        recent = [] if alarm else [(window, twin, spread)] + recent[:LOOKBACK - 2]
        after = dataclasses.replace(after, statistics=_with_recent(after.statistics, recent))
        record = {
            "index": len(timeline),
            "source": str(source),
            "t_start": float(np.asarray(data["t"]).reshape(-1)[0] if t_start is None else t_start),
            "alarm": bool(alarm),
            "new_terms": new,
            "dropped_terms": dropped,
            "changed_terms": changed,
            "seconds": round(time.perf_counter() - start, 4),
            "equations": [e.to_json() for e in after.equations],
            "p_value": p_combined,
            "p_window": p_window,
            "pooled": [test_p_value(t) for t in tests],
            "test": [{"state": e.state, "statistic": float(stat[j]), "df": int(df[j]),
                      "dispersion": float(dispersion[j]), "p_all": float(p_all[j]),
                      "term": e.names[int(term[j])], "z": float(z[j]), "p_term": float(p_term[j]),
                      "p_linear": float(p_linear[j]), "p_value": float(p[j])} for j, e in enumerate(drift)],
            "restarted": bool(alarm),
            "window_estimates": window_estimates(after, window, _regressed(before, timeline)),
            "data_sha256": data_fingerprint(data),
        }
        history = list(after.history)
        history[-1] = {**history[-1], "monitor": record}
        self.twin = dataclasses.replace(after, history=history)
        return record
