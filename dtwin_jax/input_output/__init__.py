"""Framework 1, input-output: states (or some of them), the force and optionally the rates
measured. The targets and their statistics (`targets`), the update by sensor layout
(`update`), the regression on accelerometers alone (`accelerometers`) and the output-error
refinement (`output_error`)."""
