"""kftune.report."""
