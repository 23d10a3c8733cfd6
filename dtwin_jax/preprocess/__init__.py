"""Preprocessing: from measurements to what the regression needs. The noise model and
Savitzky-Golay filters (`measurement`), the one Kalman filter (`kalman`), the kinematic
smoother (`denoise`), the state-space smoother of partial states (`estimate`), the weak
form (`weak_form`, `weak_form_accelerometers`), states from accelerometers
(`accelerometers`) and a closed loop's reference as an instrument (`instruments`)."""
