"""Following one structure in service, window after window (formats.md, "Monitoring a
structure in service").

Each window is first tested against the twin as it stood before it
(:func:`~dtwin_jax.monitor.change.window_test`; a change that persists also by the window
together with the one or two before it, :func:`combined_p_value`; false-alarm rate
``false_alarm`` per window), then absorbed: without an alarm the twin is re-updated with the older data
discounted by ``forget``; after an alarm it restarts from the nominal prior on the window
alone, and the alarm names its reasons (terms that appeared or disappeared, coefficients that
left their 95% interval). Every window's entry rides in the twin's history, so the twin
folder keeps the timeline, and a window whose data are already there is never absorbed
twice (a killed monitor resumes where it stopped, with the history it would have had).
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import time

import numpy as np

from dtwin_jax.errors import DataError
from dtwin_jax.monitor.change import belief, window_statistics, window_test
from dtwin_jax.update.from_data import update_from_data
from dtwin_jax.update.result import SamplerSettings, UpdateResult

__all__ = ["LOOKBACK", "MONITOR_SETTINGS", "Monitor", "alarm_reasons", "combined_p_value", "data_fingerprint",
           "first_alarm", "fisher_combination"]

# Two chains of 1000 draws: a 1 s window tested and absorbed in about 0.2 s warm on one core.
MONITOR_SETTINGS = SamplerSettings(num_chains=2, num_draws=1000, num_burnin=500)
RESTART_PRIOR = "spike-and-slab (restarted: the window disagreed with the twin)"
# A change that persists is tested on this window and up to LOOKBACK - 1 before it (since the
# last restart) together: Fisher's combination of their p-values.
LOOKBACK = 3


def fisher_combination(p_values) -> float:
    """P-value of Fisher's combination of ``L`` independent p-values: ``-2 sum log p`` is
    chi-square with ``2 L`` degrees of freedom, whose survival function is
    ``exp(-s) sum_{j < L} s^j / j!`` at ``s = -sum log p``."""
    p = np.clip(np.asarray(p_values, dtype=float), 1e-300, 1.0)
    s = -np.sum(np.log(p))
    return float(np.exp(-s) * sum(s**j / math.factorial(j) for j in range(p.size)))


def combined_p_value(p_window: float, earlier: list[float]) -> float:
    """The window's p-value for the alarm: the smallest of the window alone and its Fisher
    combinations with the ``1 .. LOOKBACK - 1`` windows before it (``earlier``, newest first),
    times the number of combinations tried (Bonferroni)."""
    tried = [p_window] + [fisher_combination([p_window] + earlier[:j]) for j in range(1, len(earlier) + 1)]
    return float(min(1.0, min(tried) * len(tried)))


def alarm_reasons(before: UpdateResult, after: UpdateResult) -> tuple[list[str], list[str], list[str]]:
    """What changed between two twins' drift equations, as ``"state:term"`` names.

    **Arguments:**

    - ``before``, ``after``: updates over the same library.

    **Returns:** ``(new, dropped, changed)``: terms selected after but not before, before but
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
    """SHA-256 (hex) of a window as read: ``t``, ``x``, ``u``, ``xdot`` as float64 bytes with
    their shapes, and the sensor names."""
    h = hashlib.sha256()
    for key in ("t", "x", "u", "xdot"):
        a = data.get(key)
        if a is None:
            h.update(f"{key}:none;".encode())
            continue
        a = np.ascontiguousarray(a, dtype=np.float64)
        h.update(f"{key}:{a.shape};".encode())
        h.update(a.tobytes())
    for key in ("x_names", "xdot_names"):
        h.update(f"{key}:{data.get(key)!r};".encode())
    return h.hexdigest()


def first_alarm(timeline: list[dict]) -> int | None:
    """The index of the first window with an alarm, or None."""
    return next((w["index"] for w in timeline if w.get("alarm")), None)


@dataclasses.dataclass
class Monitor:
    """A twin that follows its structure: :meth:`step` tests and absorbs one window.

    **Arguments:**

    - ``twin``: the baseline :class:`~dtwin_jax.update.UpdateResult` (a saved twin's
      :func:`~dtwin_jax.io.store.load_twin`, or a fresh update), either framework.
    - ``false_alarm``: the chance that a window that follows the twin raises an alarm, in
      (0, 1) (split evenly over the drift equations).
    - ``forget``: the weight, in [0, 1], of the older windows' data at each update (0.9:
      about ten windows' memory, so a slow drift is followed).
    - ``settings``: the sampler's, per window.
    - ``seed``: window ``h`` of the history is sampled with seed ``seed + h``, so a resumed
      run repeats an uninterrupted one.
    - ``smoothing``: as :func:`~dtwin_jax.update.update_input_output`'s.
    """

    twin: UpdateResult
    false_alarm: float = 1e-3
    forget: float = 0.9
    settings: SamplerSettings = MONITOR_SETTINGS
    seed: int = 0
    smoothing: object = "auto"

    def __post_init__(self):
        if not 0.0 < self.false_alarm < 1.0:
            raise DataError(f"the false-alarm rate must be in (0, 1), got {self.false_alarm:g}")
        if not 0.0 <= self.forget <= 1.0:
            raise DataError(f"forget must be in [0, 1], got {self.forget:g}")
        if not any(e.kind == "drift" for e in self.twin.equations):
            raise DataError("the twin has no drift equation to monitor")

    @property
    def timeline(self) -> list[dict]:
        """Every monitored window's entry (formats.md's ``windows``), oldest first."""
        return [h["monitor"] for h in self.twin.history if isinstance(h, dict) and isinstance(h.get("monitor"), dict)]

    def absorbed(self, data: dict) -> bool:
        """Whether a window with exactly these data is already in the timeline (a resumed
        run skips it: no window counts twice)."""
        fp = data_fingerprint(data)
        return any(w.get("data_sha256") == fp for w in self.timeline)

    def _earlier(self) -> list[float]:
        """The window-alone p-values of up to ``LOOKBACK - 1`` windows before this one, newest
        first, back to the last restart (a restarted window tested the twin it replaced)."""
        out = []
        for w in reversed(self.timeline):
            if w.get("restarted") or len(out) == LOOKBACK - 1 or not isinstance(w.get("p_window"), float):
                break
            out.append(w["p_window"])
        return out

    def _update(self, data: dict, source: str, previous, seed: int) -> UpdateResult:
        t = self.twin
        return update_from_data(t.mode, t.nominal, data, library=t.library,
                                diffusion_library=t.preprocessing.get("diffusion_library"), smoothing=self.smoothing,
                                source=source, pip_threshold=t.pip_threshold, settings=self.settings, seed=seed,
                                previous=previous, forget=self.forget)

    def step(self, data: dict, *, source: str = "window", t_start: float | None = None) -> dict:
        """Test the window ``data`` against the twin, then absorb it.

        **Arguments:**

        - ``data``: the window, as :func:`dtwin_jax.io.load_measurements` returns a file
          (``t``, ``x``, ``u``, ``xdot``, ``x_names``, ``xdot_names``).
        - ``source``: the window's name in the timeline.
        - ``t_start``: its start in service time, s (default its first sample time).

        **Returns:** the window's entry of the timeline (formats.md), also appended to the
        twin's history: ``index``, ``source``, ``t_start``, ``alarm``, ``new_terms``,
        ``dropped_terms``, ``changed_terms``, ``seconds``, ``equations``, and ``p_value`` (the
        alarm's: :func:`combined_p_value`), ``p_window`` (this window's alone, over every drift
        equation), ``test`` (each equation's statistic, degrees of freedom and p-value),
        ``restarted`` and ``data_sha256`` (:func:`data_fingerprint`).
        """
        start = time.perf_counter()
        before = self.twin
        seed = self.seed + len(before.history)
        after = self._update(data, source, before, seed)
        test = window_test(belief(before), window_statistics(after, before, self.forget))
        stat, df, p_all, term, z, p_term, p = (np.asarray(a) for a in test)
        p_window = float(min(1.0, p.min() * p.size))  # Bonferroni over the equations
        p_combined = combined_p_value(p_window, self._earlier())
        alarm = p_combined < self.false_alarm
        new = dropped = changed = []
        if alarm:  # the older data no longer describe the structure: start again from this window
            fresh = self._update(data, source, None, seed)
            entry = {**fresh.history[-1], "update": len(before.history) + 1, "prior": RESTART_PRIOR}
            after = dataclasses.replace(fresh, history=list(before.history) + [entry])
            new, dropped, changed = alarm_reasons(before, after)
        drift = [e for e in before.equations if e.kind == "drift"]
        record = {
            "index": len(self.timeline),
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
            "test": [{"state": e.state, "statistic": float(stat[j]), "df": int(df[j]), "p_all": float(p_all[j]),
                      "term": e.names[int(term[j])], "z": float(z[j]), "p_term": float(p_term[j]),
                      "p_value": float(p[j])} for j, e in enumerate(drift)],
            "restarted": bool(alarm),
            "data_sha256": data_fingerprint(data),
        }
        history = list(after.history)
        history[-1] = {**history[-1], "monitor": record}
        self.twin = dataclasses.replace(after, history=history)
        return record
