"""kftune.data."""
