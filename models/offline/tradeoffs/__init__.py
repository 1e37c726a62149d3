"""The offline trade-off studies: the speed–accuracy frontier of the serving path (frontier), stability
where methods fail (robustness), calibrated intervals and out-of-distribution flags (coverage),
and the report that gathers them (report). Run by `hapticlink tradeoffs …`."""

from pathlib import Path

DEFAULT_WORK = Path("artifacts") / "tradeoffs"  # per-texture intermediates: git-ignored, never committed
DEFAULT_REPORT = Path("reports") / "tradeoffs"
