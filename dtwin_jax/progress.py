"""Progress of an update's stages on standard error (tqdm), for the command line and for
notebooks: one bar step per stage, its name shown while it runs, so that no stage that takes
seconds (compilation included) runs silently."""

from __future__ import annotations

import contextlib
import time

__all__ = ["Stages"]


class Stages:
    """``stages = Stages(enabled, total, "update")``; ``with stages("sampling"): ...``.

    ``total``: the number of stages announced (the bar's length). Disabled: no output and
    no tqdm import. ``seconds`` maps each stage to its wall time (kept either way; JAX runs
    asynchronously, so a stage should end by blocking on its results)."""

    def __init__(self, enabled: bool, total: int, desc: str):
        self.seconds: dict[str, float] = {}
        self._bar = None
        if enabled:
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total, desc=desc, unit="stage", leave=False,
                             bar_format="{desc}: {n_fmt}/{total_fmt} stages [{elapsed}]{postfix}")

    @contextlib.contextmanager
    def __call__(self, name: str):
        start = time.perf_counter()
        if self._bar is not None:
            self._bar.set_postfix_str(name)
        yield
        self.seconds[name] = round(time.perf_counter() - start, 3)
        if self._bar is not None:
            self._bar.update(1)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
