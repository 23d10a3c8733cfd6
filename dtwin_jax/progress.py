"""Progress on standard error (tqdm), for the command line and for notebooks; drawn only
where it can be (a terminal or a Jupyter kernel, `draws_bars`), never into a file or a pipe.

* `Stages`: an update's stages, one bar step each, its name shown while it runs, so
  that no stage that takes seconds (compilation included) runs silently.
* `Bar` and `tick`: progress from inside a compiled program (the sampler's
  sweeps, a study's problems): the program calls `jax.debug.callback(tick, n)` and the
  open bar, if any, advances by `n`.
"""

from __future__ import annotations

import contextlib
import sys
import time

__all__ = ["Stages", "Bar", "tick", "draws_bars"]

_BAR: list = [None]  # the open Bar's tqdm, which tick() advances


def draws_bars() -> bool:
    """Whether progress can be drawn: standard error is a terminal, or this is a Jupyter kernel.

    tqdm.auto draws a widget in a Jupyter kernel. Redrawn bars in a file or a pipe are carriage
    returns and escape codes that bury the messages a user or a script reads.

    **Returns:** True where bars can be drawn, False otherwise (also for a replaced or closed
    standard error).
    """
    if "ipykernel" in sys.modules:
        return True
    try:
        return sys.stderr is not None and sys.stderr.isatty()
    except (AttributeError, ValueError):  # a replaced or closed stream
        return False


def tick(n=1) -> None:
    """Advance the open `Bar` by `n` (a host callback; nothing when none is open).

    **Arguments:**

    - `n`: the number of steps, an integer or a scalar array (default 1).
    """
    if _BAR[0] is not None:
        _BAR[0].update(int(n))


class Bar:
    """`with Bar(show, total, desc):` a tqdm bar that `tick` advances, or nothing.

    Nothing is drawn when `show` is False, `draws_bars` is False, or a bar is already open
    (then the outer bar counts).

    **Arguments:**

    - `show`: whether to draw the bar at all.
    - `total`: the number of steps the bar counts to.
    - `desc`: the bar's label.
    """

    def __init__(self, show: bool, total: int, desc: str):
        self.show, self.total, self.desc = show, total, desc

    def __enter__(self):
        # Inside an open bar (an update's, over every equation) the outer bar counts.
        self._own = self.show and _BAR[0] is None and draws_bars()
        if self._own:
            from tqdm.auto import tqdm

            _BAR[0] = tqdm(total=self.total, desc=self.desc, leave=False)
        return self

    def __exit__(self, *exc):
        if self._own:
            _BAR[0].close()
            _BAR[0] = None
        return False


class Stages:
    """`stages = Stages(enabled, total, "update")`; `with stages("sampling"): ...`.

    Disabled, or where `draws_bars` is False: no output and no tqdm import. `seconds` maps
    each stage to its wall time in s (kept either way; JAX runs asynchronously, so a stage
    should end by blocking on its results).

    **Arguments:**

    - `enabled`: whether to draw the bar.
    - `total`: the number of stages announced (the bar's length).
    - `desc`: the bar's label.
    """

    def __init__(self, enabled: bool, total: int, desc: str):
        self.seconds: dict[str, float] = {}
        self._bar = None
        if enabled and draws_bars():
            from tqdm.auto import tqdm

            self._bar = tqdm(total=total, desc=desc, unit="stage", leave=False,
                             bar_format="{desc}: {n_fmt}/{total_fmt} stages [{elapsed}]{postfix}")

    @contextlib.contextmanager
    def __call__(self, name: str):
        """Run one stage: show its name while it runs, then record its wall time and step the bar.

        On an error or Ctrl-C inside the stage the bar is closed before the exception propagates.

        **Arguments:**

        - `name`: the stage's name, shown beside the bar and the key in `seconds`.

        **Returns:** a context manager (it yields None) around the stage's work.
        """
        start = time.perf_counter()
        if self._bar is not None:
            self._bar.set_postfix_str(name)
        try:
            yield
        except BaseException:  # Ctrl-C or an error: clear the bar before the one-line message
            self.close()
            raise
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
