"""Monitoring structures in service: each window tested against the twin as it stood
before it, then absorbed (formats.md, "Monitoring a structure in service")."""

from dtwin_jax.monitor.change import (
           ChangeTest,
           window_statistics,
           window_test,
)
from dtwin_jax.monitor.service import (
           FALSE_ALARM,
           MONITOR_SETTINGS,
           Monitor,
           alarm_reasons,
           data_fingerprint,
           first_alarm,
)

__all__ = ["ChangeTest", "window_statistics", "window_test", "FALSE_ALARM", "MONITOR_SETTINGS", "Monitor",
           "alarm_reasons", "data_fingerprint", "first_alarm"]
