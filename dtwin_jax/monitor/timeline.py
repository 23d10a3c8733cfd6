"""A monitor's timeline as files: `MONITOR.json` (formats.md) and `MONITOR.csv`, one row
per window with every term that was ever selected (its PIP, mean and 95% interval)."""

from __future__ import annotations

import csv
import io

from dtwin_jax.monitor.service import first_alarm

__all__ = ["ever_selected", "timeline_json", "timeline_csv", "write_timeline"]

_FIXED = ("index", "source", "t_start", "alarm", "p_value", "p_window", "restarted", "seconds")
_REASONS = ("new_terms", "dropped_terms", "changed_terms")


def timeline_json(timeline: list[dict], **settings) -> dict:
    """The timeline as the `MONITOR.json` object (formats.md).

    **Arguments:**

    - `timeline`: the monitor's windows, one dict each (`Monitor.timeline`).
    - `**settings`: further keys to record (the false-alarm rate and the forgetting factor, say).

    **Returns:** `{"windows": [...], "first_alarm": index or None, **settings}`, ready for JSON.
    """
    return {"windows": list(timeline), "first_alarm": first_alarm(timeline), **settings}


def ever_selected(timeline: list[dict]) -> list[tuple[str, str, str]]:
    """Every term selected in some window of a timeline, in order of first selection.

    **Arguments:**

    - `timeline`: the monitor's windows, one dict each (`Monitor.timeline`).

    **Returns:** a list of `(state, kind, term)` string triples, `kind` being `"drift"` or `"diffusion"`.
    """
    seen = {}
    for w in timeline:
        for e in w.get("equations", []):
            for term in e.get("terms", []):
                seen.setdefault((e.get("state"), e.get("kind"), term.get("expr")), None)
    return list(seen)


def timeline_csv(timeline: list[dict]) -> str:
    """The timeline as the text of `MONITOR.csv`, one row per window.

    The columns: the fixed ones, the reasons (`;`-joined `state:term`), then `pip`, `mean`,
    `lower` and `upper` (95% HDI) of every term ever selected, named `pip[x2:x1**3]`
    (`[x2 diffusion:1]` for a diffusion term); empty where not selected.

    **Arguments:**

    - `timeline`: the monitor's windows, one dict each (`Monitor.timeline`).

    **Returns:** the CSV text, a header row then one row per window, each line ending in a newline.
    """
    terms = ever_selected(timeline)
    label = [f"{s}:{t}" if k == "drift" else f"{s} {k}:{t}" for s, k, t in terms]
    header = list(_FIXED) + list(_REASONS) + [f"{q}[{lab}]" for lab in label for q in ("pip", "mean", "lower", "upper")]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    for w in timeline:
        row = [w.get(c) for c in _FIXED] + [";".join(w.get(c, [])) for c in _REASONS]
        eqs = {(e.get("state"), e.get("kind")): e for e in w.get("equations", [])}
        for s, k, t in terms:
            e = eqs.get((s, k), {})
            hit = next((term for term in e.get("terms", []) if term.get("expr") == t), None)
            pip = e.get("pip", {}).get(t)
            row += [pip] + ([hit["mean"], *hit["hdi_95"]] if hit else ["", "", ""])
        writer.writerow(["" if v is None else v for v in row])
    return out.getvalue()


def write_timeline(path, timeline: list[dict], *, csv_path=None, **settings) -> None:
    """Write `MONITOR.json` (and `MONITOR.csv`), each atomically.

    **Arguments:**

    - `path`: where to write `MONITOR.json`.
    - `timeline`: the monitor's windows, one dict each (`Monitor.timeline`).
    - `csv_path`: where to write `MONITOR.csv`, or None (default) for no CSV file.
    - `**settings`: further keys for the JSON file (see `timeline_json`).
    """
    from dtwin_jax.io import atomic_path, write_json

    write_json(path, timeline_json(timeline, **settings))
    if csv_path is not None:
        with atomic_path(csv_path) as tmp:
            with open(tmp, "w", newline="") as f:
                f.write(timeline_csv(timeline))
