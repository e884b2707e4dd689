"""A run directory for a person: ``report.md`` with its figures, and the Rerun recording ``run.rrd``."""
