"""One update from a measurement dictionary (`dtwin_jax.io.load_measurements`): the
framework's entry point chosen by the mode and the sensor layout, shared by the command line
and the monitor."""

from __future__ import annotations

from dtwin_jax.errors import DataError

__all__ = ["update_from_data"]


def update_from_data(mode: str, nominal, data: dict, *, library, diffusion_library=None, smoothing="auto",
                     refine: bool = False, source: str = "the data", **common):
    """Update `nominal` from `data` in `mode`.

    Calls `update_input_output` or `update_output_only`. A layout the mode cannot use is a
    one-line `DataError`.

    **Arguments:**

    - `mode`: `"input-output"` or `"output-only"`.
    - `nominal`: the nominal model, a `dtwin_jax.models.systems.LinearSecondOrder`.
    - `data`: `t`, `x` and optional `u`, `xdot`, `x_names`, `xdot_names`,
      `u_interpolation`, `reference`, as `dtwin_jax.io.load_measurements` returns them
      (`u` required for input-output).
    - `library`: the (drift) library, a spec or a `Library`, as the update functions'.
    - `diffusion_library`: output-only: the diffusion's library, as `update_output_only`'s;
      None (default) its default.
    - `smoothing`: input-output: as `update_input_output`'s (default `"auto"`).
    - `refine`: input-output: refine by output error, as `update_input_output`'s (output-only
      refuses True).
    - `source`: how a message names the data (a file name).
    - `**common`: `pip_threshold`, `settings`, `seed`, `progress`, `previous`,
      `forget`, `allow_repeat`, passed to the update function.

    **Returns:** the `dtwin_jax.update.UpdateResult`.
    """
    if mode == "output-only":
        if refine:
            raise DataError("--refine needs input-output data (output error simulates the measured input)")
        from dtwin_jax.output_only.update import update_output_only

        if "x" not in data:  # accelerometers alone: ambient vibration
            return update_output_only(nominal, data["t"], None, xdot=data["xdot"], xdot_names=data.get("xdot_names"),
                                      library=library, diffusion_library=diffusion_library, **common)
        if data.get("x_names") not in (None, list(nominal.state_names)) or "xdot" in data:
            raise DataError("output-only mode needs every state measured (no 'x_names' subset, no 'xdot')")
        return update_output_only(nominal, data["t"], data["x"], library=library,
                                  diffusion_library=diffusion_library, **common)
    if "u" not in data:
        raise DataError(f"input-output mode needs key 'u' in '{source}'")
    from dtwin_jax.input_output.update import update_input_output

    return update_input_output(nominal, data["t"], data.get("x"), data["u"], data.get("xdot"),
                               x_names=data.get("x_names"), xdot_names=data.get("xdot_names"),
                               interpolation=data.get("u_interpolation", "auto"),
                               library=library, smoothing=smoothing, refine=refine,
                               reference=data.get("reference"), **common)
