"""Frame sources: data sets and logs that yield :class:`driftmap.Frame` objects in time order."""

from driftmap.sources.synthetic import SyntheticLog, SyntheticLogConfig, generate_synthetic_log

__all__ = ["SyntheticLog", "SyntheticLogConfig", "generate_synthetic_log"]
