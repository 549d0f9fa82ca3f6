"""kftune.tuning."""
