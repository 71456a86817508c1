"""The version of driftmap (one place; ``driftmap --version``, stores and reports record it)."""

__version__ = "0.1.0"
