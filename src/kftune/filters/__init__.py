"""kftune.filters."""
